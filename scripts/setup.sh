#!/usr/bin/env bash
# Makes a fresh Debian machine ready to build and test skyherd. Idempotent: every step checks
# first and says what it installs; a second run on a ready machine takes a few seconds.
set -euo pipefail
cd "$(dirname "$0")/.."

PYMAVLINK_VERSION=2.4.49
# MAVSDK's Python API with its bundled mavsdk_server (the `mavsdk` 4.1 wheel no longer bundles
# it): the conformance test flies the mock PX4 with it.
MAVSDK_GRPC_VERSION=4.0.5
say() { printf 'setup: %s\n' "$*"; }

# 1. The pinned Rust toolchain and its cross targets (read from rust-toolchain.toml).
if ! command -v rustup >/dev/null 2>&1; then
  say "rustup is missing: install Rust from your distribution or rustup first" >&2
  exit 1
fi
toolchain=$(sed -n 's/^channel *= *"\(.*\)"/\1/p' rust-toolchain.toml)
installed_targets=$(rustup target list --installed --toolchain "$toolchain" 2>/dev/null || true)
for target in aarch64-unknown-linux-gnu thumbv7em-none-eabihf; do
  if ! grep -qx "$target" <<<"$installed_targets"; then
    say "installing toolchain $toolchain with target $target"
    rustup toolchain install "$toolchain" --profile minimal --component rustfmt,clippy --target "$target"
  fi
done
for component in rustfmt clippy; do
  if ! rustup component list --installed --toolchain "$toolchain" | grep -q "^$component"; then
    say "installing $component"
    rustup component add --toolchain "$toolchain" "$component"
  fi
done

# 2. Debian packages: aarch64 cross linker + libc, qemu-user to run aarch64 binaries,
#    llvm for llvm-size on the Cortex-M firmware, python venv support for the test peers.
need=()
command -v aarch64-linux-gnu-gcc >/dev/null 2>&1 || need+=(gcc-aarch64-linux-gnu)
[ -d /usr/aarch64-linux-gnu/lib ] || need+=(libc6-dev-arm64-cross)
command -v qemu-aarch64 >/dev/null 2>&1 || need+=(qemu-user)
command -v llvm-size >/dev/null 2>&1 || need+=(llvm)
command -v file >/dev/null 2>&1 || need+=(file)
python3 -c 'import venv, ensurepip' >/dev/null 2>&1 || need+=(python3-venv)
if [ ${#need[@]} -gt 0 ]; then
  say "installing Debian packages: ${need[*]}"
  export DEBIAN_FRONTEND=noninteractive
  sudo_cmd=""
  [ "$(id -u)" -eq 0 ] || sudo_cmd="sudo"
  $sudo_cmd apt-get update -qq
  $sudo_cmd apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
fi

# 3. Python test peers: pymavlink as an independent MAVLink implementation.
if ! .venv/bin/python -c "import pymavlink, sys; sys.exit(0 if pymavlink.__version__ == '$PYMAVLINK_VERSION' else 1)" >/dev/null 2>&1; then
  say "creating .venv with pymavlink==$PYMAVLINK_VERSION"
  python3 -m venv .venv
  .venv/bin/pip install -q --disable-pip-version-check "pymavlink==$PYMAVLINK_VERSION"
fi

if ! .venv/bin/python -c "import importlib.metadata as m, sys; sys.exit(0 if m.version('mavsdk-grpc') == '$MAVSDK_GRPC_VERSION' else 1)" >/dev/null 2>&1; then
  say "installing mavsdk-grpc==$MAVSDK_GRPC_VERSION into .venv (MAVSDK conformance test)"
  .venv/bin/pip install -q --disable-pip-version-check "mavsdk-grpc==$MAVSDK_GRPC_VERSION"
fi

# 4. A real ArduCopter SITL for the autopilot e2e test: SKYHERD_ARDUCOPTER, else the prebuilt
#    one in ../shared/ardupilot-sitl, else build the same pinned commit into .arducopter/.
if [ -n "${SKYHERD_ARDUCOPTER:-}" ] && [ -e "$SKYHERD_ARDUCOPTER" ]; then
  say "ArduCopter SITL: $SKYHERD_ARDUCOPTER (SKYHERD_ARDUCOPTER)"
elif [ -x ../shared/ardupilot-sitl/arducopter ]; then
  say "ArduCopter SITL: ../shared/ardupilot-sitl/arducopter"
elif [ -x .arducopter/arducopter ]; then
  say "ArduCopter SITL: .arducopter/arducopter"
else
  say "no ArduCopter SITL found: building the pinned commit (scripts/build-arducopter.sh, ~6 min)"
  ./scripts/build-arducopter.sh
fi

say "ready (toolchain $toolchain, aarch64 + thumbv7em targets, cross gcc, qemu-aarch64, pymavlink $PYMAVLINK_VERSION, mavsdk-grpc $MAVSDK_GRPC_VERSION, ArduCopter SITL)"
