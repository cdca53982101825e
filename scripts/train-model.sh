#!/usr/bin/env bash
# Trains the shipped model from nothing, as models/MODEL.md records it: stage 1 (warm start,
# MTDDPG, first evolution stage; about 32 min on the 2-core development machine), stage 2 (the
# second evolution stage; about 18 min), then the export (quantization-aware fine-tuning and
# int8/int16 quantization; about 20 s); then mtddpg-v3 from mtddpg-v1's float actor, widened to
# encoder v4's features: the Enclose rule distilled into its large flocks (about 4 min) and its
# export; then mtddpg-room, the indoor mission's model with the drones' dynamics on, from
# mtddpg-v3's float actor: two evolution stages on the room (about 7 and 11 min) and its export.
# About 75 min in all. Seeded: the same commands give the same model files.
#   ./scripts/train-model.sh            # -> models/mtddpg-v1.skym, models/mtddpg-v3.skym,
#                                       #    models/mtddpg-room.skym and their float actors in
#                                       #    trainer/shipped/
set -euo pipefail
cd "$(dirname "$0")/.."
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-target-trainer}"
cargo build --release --locked -p skyherd-trainer
trainer="$CARGO_TARGET_DIR/release/skyherd-trainer"
"$trainer" train --config trainer/configs/mtddpg-v1.toml
"$trainer" evolve --config trainer/configs/mtddpg-v1-refine.toml \
  --checkpoint runs/mtddpg-v1/evolved.safetensors
"$trainer" export --checkpoint runs/mtddpg-v1-refine/evolved.safetensors \
  --out models/mtddpg-v1.skym --actor-out trainer/shipped/mtddpg-v1.actor.safetensors
"$trainer" distill --config trainer/configs/mtddpg-v3-distill.toml \
  --actor runs/mtddpg-v1-refine/evolved.safetensors --out runs/mtddpg-v3/distilled.safetensors \
  | tee trainer/shipped/mtddpg-v3-distill.log.txt
"$trainer" export --checkpoint runs/mtddpg-v3/distilled.safetensors \
  --out models/mtddpg-v3.skym --actor-out trainer/shipped/mtddpg-v3.actor.safetensors
"$trainer" evolve --config trainer/configs/mtddpg-room.toml \
  --actor runs/mtddpg-v3/distilled.safetensors
"$trainer" evolve --config trainer/configs/mtddpg-room-2.toml \
  --checkpoint runs/mtddpg-room/evolved.safetensors
"$trainer" export --checkpoint runs/mtddpg-room-2/evolved.safetensors \
  --out models/mtddpg-room.skym --actor-out trainer/shipped/mtddpg-room.actor.safetensors
