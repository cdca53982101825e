#!/usr/bin/env bash
# Makes a fresh Debian machine ready to build and test skyherd. Idempotent: every step checks
# first and says what it installs; a second run on a ready machine takes a few seconds.
set -euo pipefail
cd "$(dirname "$0")/.."

PYMAVLINK_VERSION=2.4.49
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

say "ready (toolchain $toolchain, aarch64 + thumbv7em targets, cross gcc, qemu-aarch64, pymavlink $PYMAVLINK_VERSION)"
