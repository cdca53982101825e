#!/usr/bin/env bash
# Every check CI runs, in order, from a fresh machine: set-up, format, lints, the no_std
# Cortex-M build, the firmware-shaped build, the aarch64 daemon under qemu, the tests, docs.
# `.ci/run` runs exactly this, with no argument (all steps).
#
#   ./scripts/test.sh                 # every step, as CI does
#   ./scripts/test.sh clippy test     # chosen steps, in the order given (set-up always runs)
#   ./scripts/test.sh --list          # the step names
set -euo pipefail
cd "$(dirname "$0")/.."

ALL_STEPS=(fmt clippy nostd firmware aarch64 test doc)
start=$(date +%s)
say() { printf '\n==> [%4ss] %s\n' "$(( $(date +%s) - start ))" "$*"; }
target_dir="${CARGO_TARGET_DIR:-$PWD/target}"
daemon="$target_dir/aarch64-unknown-linux-gnu/release/skyherd-onboard"

step_fmt() {
  say "fmt: cargo fmt --check"
  cargo fmt --all --check
}

step_clippy() {
  say "clippy: workspace, all targets, warnings denied"
  cargo clippy --workspace --all-targets --locked -- -D warnings
}

step_nostd() {
  say "nostd: the model format and the onboard core for thumbv7em-none-eabihf (no default features)"
  cargo build --locked -p skyherd-model -p skyherd-onboard --no-default-features --target thumbv7em-none-eabihf
}

step_firmware() {
  say "firmware: the firmware-shaped example for thumbv7em-none-eabihf, and its size"
  (cd onboard/firmware && cargo build --locked --release --target thumbv7em-none-eabihf)
  llvm-size "${CARGO_TARGET_DIR:-onboard/firmware/target}/thumbv7em-none-eabihf/release/skyherd-firmware-example"
}

step_aarch64() {
  say "aarch64: release build of the onboard daemon, run under qemu-aarch64"
  cargo build --locked --release --target aarch64-unknown-linux-gnu -p skyherd-daemon --bin skyherd-onboard
  file "$daemon" | tee /dev/stderr | grep -q 'ARM aarch64'
  qemu-aarch64 -L /usr/aarch64-linux-gnu "$daemon" self-test
}

step_test() {
  say "test: cargo test (workspace; the SITL tests fly the aarch64 daemon too when it was built)"
  if [ -x "$daemon" ]; then
    SKYHERD_AARCH64_DAEMON="$daemon" cargo test --workspace --locked
  else
    echo "(no aarch64 daemon at $daemon: run the aarch64 step first to fly it in the SITL tests)"
    cargo test --workspace --locked
  fi
}

step_doc() {
  say "doc: cargo doc (warnings denied)"
  RUSTDOCFLAGS="-D warnings" cargo doc --workspace --no-deps --locked
}

if [ "${1:-}" = "--list" ]; then
  printf '%s\n' "${ALL_STEPS[@]}"
  exit 0
fi
steps=("$@")
[ ${#steps[@]} -gt 0 ] || steps=("${ALL_STEPS[@]}")
for name in "${steps[@]}"; do
  if ! declare -F "step_$name" >/dev/null; then
    echo "test.sh: unknown step '$name'; steps are: ${ALL_STEPS[*]}" >&2
    exit 2
  fi
done

say "set-up"
./scripts/setup.sh
for name in "${steps[@]}"; do
  "step_$name"
done
say "${steps[*]}: passed in $(( $(date +%s) - start )) s"
