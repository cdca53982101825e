#!/usr/bin/env bash
# SITL missions over a range of seeds, and a summary: success, median and range of mission
# time, missions within 30 s, closest approach, separation breaches, lockstep misses.
#   ./scripts/sitl-seeds.sh OUT_DIR FIRST LAST [skyherd-sitl flags...]
#   ./scripts/sitl-seeds.sh runs/sitl-indoor 416 431             # the default indoor flight
# Each mission's result.json stays in OUT_DIR/seed-K/; the summary goes to stdout.
set -euo pipefail
cd "$(dirname "$0")/.."
out="$1"; first="$2"; last="$3"; shift 3
cargo build --quiet --release --locked -p skyherd-sitl -p skyherd-ground -p skyherd-daemon --bins
for seed in $(seq "$first" "$last"); do
  target/release/skyherd-sitl --seed "$seed" --out "$out/seed-$seed" "$@" \
    > "$out/seed-$seed.log" 2>&1 || true
done
python3 - "$out" "$first" "$last" <<'PY'
import json, statistics, sys
out, first, last = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
rows = []
for seed in range(first, last + 1):
    try:
        rows.append((seed, json.load(open(f"{out}/seed-{seed}/result.json"))))
    except (OSError, ValueError) as e:
        print(f"seed {seed}: no result ({e})")
won = [r for _, r in rows if r["success"]]
times = sorted(r["mission_time_s"] for r in won)
closest = [r["min_separation_m"] for _, r in rows if r.get("min_separation_m") is not None]
print(f"seeds {first}-{last}: {len(won)} of {len(rows)} succeed", end="")
if times:
    print(f", median {statistics.median(times):.1f} s ({times[0]:.1f}-{times[-1]:.1f} s), "
          f"{sum(t <= 30.0 for t in times)} within 30 s", end="")
print()
if closest:
    print(f"closest approach {min(closest):.2f} m; breaches in "
          f"{sum(r['separation_breaches'] > 0 for _, r in rows)} missions; lockstep misses "
          f"{sum(r['lockstep_misses'] for _, r in rows)}")
for seed, r in rows:
    if not r["success"]:
        print(f"  seed {seed}: {r['ending']}")
PY
