#!/usr/bin/env python3
"""A model's paper-protocol sweep beside the rules': one Markdown table.

    scripts/compare-with-rules.py MODEL_RESULTS.json [BASELINE_RESULTS.json ...] > comparison.md

The baselines default to docs/baselines/results.json and docs/baselines/enclose/results.json. All
files are `skyherd-sim eval --out-dir` results on the same seeds. Each row is one
(task, M, N) of the model's sweep: its success and time over the lower bound, Lama's, and the
best rule's (highest success, then lowest time ratio).
"""
import json
import sys


def main() -> None:
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    model_rows = json.load(open(sys.argv[1]))
    paths = sys.argv[2:] or ["docs/baselines/results.json", "docs/baselines/enclose/results.json"]
    baselines = [row for path in paths for row in json.load(open(path))]
    rules = {}
    for r in baselines:
        rules.setdefault((r["task"], r["herders"], r["targets"]), []).append(r)
    name = model_rows[0]["method"] if model_rows else "model"
    pct = lambda r: f"{100 * r['success_rate']:.0f} %"
    ratio = lambda r: f"{r['mean_time_ratio']:.2f}" if r["successes"] else "-"
    print(f"| task | M | N | {name} success | time / bound | Lama success | time / bound | best rule (success, time / bound) |")
    print("|---|---|---|---|---|---|---|---|")
    for r in model_rows:
        key = (r["task"], r["herders"], r["targets"])
        m = r["herders"] if r["herders"] != "adaptive" else f"adaptive ({r['herder_count']})"
        others = rules.get(key, [])
        lama = next((o for o in others if o["method"] == "lama"), None)
        best = max(others, key=lambda o: (o["success_rate"], -o["mean_time_ratio"] if o["successes"] else -1e9), default=None)
        lama_cells = f"{pct(lama)} | {ratio(lama)}" if lama else "- | -"
        best_cell = f"{best['method']} ({pct(best)}, {ratio(best)})" if best else "-"
        print(f"| {r['task']} | {m} | {r['targets']} | {pct(r)} | {ratio(r)} | {lama_cells} | {best_cell} |")


if __name__ == "__main__":
    main()
