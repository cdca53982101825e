#!/usr/bin/env bash
# Every check CI runs, in order, from a fresh machine: set-up, format, lints, tests, the
# no_std Cortex-M build, the aarch64 daemon under qemu, docs. `.ci/run` runs exactly this.
set -euo pipefail
cd "$(dirname "$0")/.."

start=$(date +%s)
step() { printf '\n==> [%4ss] %s\n' "$(( $(date +%s) - start ))" "$*"; }

step "set-up"
./scripts/setup.sh

step "cargo fmt --check"
cargo fmt --all --check

step "cargo clippy (workspace, all targets, warnings denied)"
cargo clippy --workspace --all-targets --locked -- -D warnings

step "no_std build of the model format and the onboard core for thumbv7em-none-eabihf (no default features)"
cargo build --locked -p skyherd-model -p skyherd-onboard --no-default-features --target thumbv7em-none-eabihf

step "firmware-shaped example for thumbv7em-none-eabihf, and its size"
(cd onboard/firmware && cargo build --locked --release --target thumbv7em-none-eabihf)
llvm-size "${CARGO_TARGET_DIR:-onboard/firmware/target}/thumbv7em-none-eabihf/release/skyherd-firmware-example"

step "aarch64 release build of the onboard daemon, run under qemu-aarch64"
cargo build --locked --release --target aarch64-unknown-linux-gnu -p skyherd-onboard --features std --bin skyherd-onboard
daemon="${CARGO_TARGET_DIR:-$PWD/target}/aarch64-unknown-linux-gnu/release/skyherd-onboard"
file "$daemon" | tee /dev/stderr | grep -q 'ARM aarch64'
qemu-aarch64 -L /usr/aarch64-linux-gnu "$daemon" self-test

step "cargo test (workspace; the SITL tests fly the aarch64 daemon above under qemu too)"
SKYHERD_AARCH64_DAEMON="$daemon" cargo test --workspace --locked

step "cargo doc (warnings denied)"
RUSTDOCFLAGS="-D warnings" cargo doc --workspace --no-deps --locked

step "all checks passed in $(( $(date +%s) - start )) s"
