#!/usr/bin/env bash
# The from-scratch aim, checked as the issue states it: each seed's best checkpoint, quantized,
# on 100 held-out episodes per scenario (driving and collecting, M = 4, N = 4, 8, 16, test-time
# noise), beside the Lama rule on the same episodes.
#   ./scripts/eval-seeds.sh RUNS_DIR OUT_DIR SEED_BASE SEED...
#   ./scripts/eval-seeds.sh runs/mtddpg-scratch4 docs/learning/mtddpg-scratch4 4200000000 21 22 23 24 25
# A run with restarts keeps its winner in RUNS_DIR/mtddpg-seedS/candidate-K (restarts.json).
set -euo pipefail
cd "$(dirname "$0")/.."
runs="$1"; out="$2"; base="$3"; shift 3
trainer=target/release/skyherd-trainer
scenarios=driving:4:4,driving:8:4,driving:16:4,collecting:4:4,collecting:8:4,collecting:16:4
mkdir -p "$out"
for seed in "$@"; do
  dir="$runs/mtddpg-seed$seed"
  if [ -f "$dir/restarts.json" ]; then
    winner=$(python3 -c "import json,sys;print(json.load(open(sys.argv[1]))['winner'])" "$dir/restarts.json")
    dir="$dir/candidate-$winner"
    cp "$runs/mtddpg-seed$seed/restarts.json" "$out/restarts-seed$seed.json"
  fi
  cp "$dir/eval.csv" "$out/eval-seed$seed.csv"
  # A run with finalists (eval.finalists) records their scores and which became best.safetensors.
  [ -f "$dir/finalists.csv" ] && cp "$dir/finalists.csv" "$out/finalists-seed$seed.csv"
  # The int8 models stay beside their runs; the one shipped is copied to models/ by hand.
  nice "$trainer" export --checkpoint "$dir/best.safetensors" --out "$dir/int8.skym" \
    > "$out/export-seed$seed.txt" 2>&1
  nice "$trainer" eval --model "$dir/int8.skym" --episodes 100 --seed-base "$base" \
    --scenarios "$scenarios" > "$out/held-out-seed$seed.md"
done
# The rules on the same episodes (the model column of this table is the first seed's).
first="$runs/mtddpg-seed$1"
[ -f "$first/restarts.json" ] && first="$first/candidate-$(python3 -c "import json,sys;print(json.load(open(sys.argv[1]))['winner'])" "$first/restarts.json")"
nice "$trainer" eval --model "$first/int8.skym" --episodes 100 --seed-base "$base" \
  --scenarios "$scenarios" --baselines > "$out/held-out-with-rules.md"
