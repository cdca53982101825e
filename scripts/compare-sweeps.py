#!/usr/bin/env python3
"""Two `skyherd-sim eval` sweeps of the same method side by side (results.csv of each):
success and mean time over the lower bound per task, M and N, as a Markdown table.

    scripts/compare-sweeps.py A.csv B.csv "label A" "label B" > table.md
"""
import csv
import sys


def rows(path):
    with open(path, newline="") as f:
        return {(r["task"], r["herders"], int(r["targets"])): r for r in csv.DictReader(f)}


def cell(r):
    if r is None:
        return "-"
    success = 100.0 * float(r["success_rate"])
    ratio = r["mean_time_ratio"]
    ratio = "-" if ratio in ("", "NaN", "nan") else f"{float(ratio):.2f}x"
    return f"{success:.0f} %, {ratio}"


def main():
    if len(sys.argv) != 5:
        sys.exit("usage: compare-sweeps.py A.csv B.csv LABEL_A LABEL_B")
    a, b = rows(sys.argv[1]), rows(sys.argv[2])
    keys = sorted(set(a) | set(b), key=lambda k: (k[0], k[1] != "1", k[1] != "4", k[1], k[2]))
    print(f"| task | M | N | {sys.argv[3]} | {sys.argv[4]} | success change (points) |")
    print("|---|---|---|---|---|---|")
    for k in keys:
        ra, rb = a.get(k), b.get(k)
        delta = "-"
        if ra is not None and rb is not None:
            delta = f"{100.0 * (float(rb['success_rate']) - float(ra['success_rate'])):+.0f}"
        print(f"| {k[0]} | {k[1]} | {k[2]} | {cell(ra)} | {cell(rb)} | {delta} |")


if __name__ == "__main__":
    main()
