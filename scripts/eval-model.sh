#!/usr/bin/env bash
# The learned policy's evaluation, paper protocol: the shipped int8 model as it flies (the
# onboard `Actor` through `skyherd-sim eval --methods model:...`), 100 episodes per
# configuration, test-time noise, both tasks, M = 1, 4, adaptive, N = 1..1024, the same episode
# seeds as the baseline sweep in docs/baselines (the four rules of results.json and the Enclose
# rule of enclose/results.json). Then the merged table and Fig. 3 panels beside
# the baselines, the per-configuration comparison with the best baseline, and the Fig. 4
# trajectories of the model and the CTRL-style rule on one seed.
#   ./scripts/eval-model.sh [MODEL] [OUT_DIR]      (defaults: models/mtddpg-v1.skym docs/learned)
# About 15-25 min on a 2-core machine.
set -euo pipefail
cd "$(dirname "$0")/.."
model="${1:-models/mtddpg-v1.skym}"
out="${2:-docs/learned}"
name="$(basename "$model" .skym)"
cargo build --release --locked -p skyherd-sim --bin skyherd-sim
sim=target/release/skyherd-sim
[ -n "${CARGO_TARGET_DIR:-}" ] && sim="$CARGO_TARGET_DIR/release/skyherd-sim"
mkdir -p "$out/model-only"
"$sim" eval --methods "model:$model" --episodes 100 --seed 0 --out-dir "$out/model-only"
"$sim" plot-fig3 \
  --results docs/baselines/results.json,docs/baselines/enclose/results.json,"$out/model-only/results.json" \
  --out-dir "$out" --compare "$name"
for policy in "model:$model" ctrl; do
  label="${policy#model:}"; label="$(basename "$label" .skym)"
  "$sim" plot-trajectory --policy "$policy" --targets 8 --herders 4 --seed 1 \
    --out "$out/fig4-$label"
done
