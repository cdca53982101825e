#!/usr/bin/env bash
# The main job: set up, build, and fly one software-in-the-loop herding mission on the shipped
# model — the simulator with its mock autopilots, the ground station and one onboard daemon per
# drone as separate processes talking MAVLink 2 over UDP. Arguments go to skyherd-sitl, e.g.
#   ./scripts/mission.sh --scenario paper-drive --herders 4 --targets 16
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/setup.sh
echo "mission: building the simulator, the ground station and the daemon (release; minutes on a first run)"
cargo build --quiet --release --locked -p skyherd-sitl -p skyherd-ground -p skyherd-daemon --bins
exec target/release/skyherd-sitl "$@"
