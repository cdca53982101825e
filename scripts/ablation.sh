#!/usr/bin/env bash
# The multi-task ablation, locally: MTDDPG against single-task DDPG, SEEDS seeds per arm, each
# run its own process (`skyherd-trainer train --config C --arm ARM --seed S`, which any job
# scheduler can run elsewhere), then the report into docs/learning/.
#
#   ./scripts/ablation.sh [CONFIG] [SEEDS]     # default: trainer/configs/mtddpg-scratch.toml, 5
#
# Resumable: a finished run (its `done` marker) is skipped, an interrupted one resumes from its
# last checkpoint. Runs go under `nice`, one at a time (each uses the config's threads).
set -euo pipefail
cd "$(dirname "$0")/.."
config="${1:-trainer/configs/mtddpg-scratch.toml}"
seeds="${2:-5}"
cargo build --quiet --release --locked -p skyherd-trainer
trainer=target/release/skyherd-trainer
out_dir=$(sed -n 's/^output_dir *= *"\(.*\)"/\1/p' "$config")
# Finished runs of the default config are kept in the repository (docs/learning/ablation-seedS/
# ARM-eval.csv, the runs themselves are not): they count as done here, so a fresh checkout
# goes on with the seeds not run yet.
if [ "$config" = "trainer/configs/mtddpg-scratch.toml" ]; then
  for kept in docs/learning/ablation-seed*/*-eval.csv; do
    [ -f "$kept" ] || continue
    seed=${kept#docs/learning/ablation-seed}; seed=${seed%%/*}
    arm=$(basename "$kept" -eval.csv)
    run="$out_dir/$arm-seed$seed"
    if [ ! -f "$run/done" ]; then
      mkdir -p "$run" && cp "$kept" "$run/eval.csv" && touch "$run/done"
      echo "ablation: $run restored from $kept"
    fi
  done
fi
for seed in $(seq 1 "$seeds"); do
  for arm in mtddpg single-driving single-collecting; do
    run="$out_dir/$arm-seed$seed"
    if [ -f "$run/done" ]; then
      echo "ablation: $run done, skipped"
      continue
    fi
    resume=()
    [ -f "$run/last.safetensors" ] && resume=(--resume)
    echo "ablation: $arm seed $seed -> $run"
    mkdir -p "$run"
    nice "$trainer" train --config "$config" --arm "$arm" --seed "$seed" "${resume[@]}" \
      > "$run/train.log" 2>&1
    touch "$run/done"
  done
done
"$trainer" ablation-report --runs "$out_dir" --out docs/learning
