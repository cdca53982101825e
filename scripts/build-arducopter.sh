#!/usr/bin/env bash
# Builds the ArduCopter SITL that the autopilot e2e test flies, from the same pinned upstream
# commit as the prebuilt one in ../shared/ardupilot-sitl (ArduPilot, GPLv3), into .arducopter/
# (ignored by git: the binary stays out of the repository). About 6 minutes on 2 cores.
#
#   scripts/build-arducopter.sh            # clone, configure, build, install into .arducopter/
#   SKYHERD_ARDUPILOT_SRC=/path/to/ardupilot scripts/build-arducopter.sh   # an existing checkout
#
# Needs git, a C++ toolchain (g++ >= 11), python3 with venv; the clone needs github.com.
set -euo pipefail
cd "$(dirname "$0")/.."

COMMIT=90700977c553d2dfd95a305acf1c3e098e4d9477   # "AP_Scripting: added EFI_DLA64 driver", 2025-07-21
REPO=https://github.com/ArduPilot/ardupilot.git
say() { printf 'build-arducopter: %s\n' "$*"; }

src=${SKYHERD_ARDUPILOT_SRC:-.arducopter/src}
if [ ! -d "$src/.git" ]; then
  say "cloning ArduPilot into $src"
  mkdir -p "$(dirname "$src")"
  git clone --filter=blob:none "$REPO" "$src"
fi
git -C "$src" fetch --quiet origin "$COMMIT" || true
git -C "$src" checkout --quiet "$COMMIT"
# The submodules as that commit records them (waf, mavlink, DroneCAN, littlefs, lwip).
git -C "$src" submodule update --init --recursive --quiet

say "python build environment (empy 3.3.4, pymavlink, future, lxml, pexpect, dronecan)"
python3 -m venv .arducopter/venv
.arducopter/venv/bin/pip install -q --disable-pip-version-check \
  empy==3.3.4 pymavlink future lxml pexpect dronecan

say "configuring and building ArduCopter SITL (networking off, as the prebuilt one)"
(
  cd "$src"
  PATH="$(pwd)/../venv/bin:$PATH"
  [ "$src" = ".arducopter/src" ] || PATH="$OLDPWD/.arducopter/venv/bin:$PATH"
  ./waf configure --board sitl --disable-networking --no-submodule-update
  ./waf copter -j"$(nproc)"
)

mkdir -p .arducopter/params
cp "$src/build/sitl/bin/arducopter" .arducopter/arducopter
cp "$src/Tools/autotest/default_params/copter.parm" .arducopter/params/copter.parm
say "installed .arducopter/arducopter ($(git -C "$src" rev-parse --short HEAD))"
