#!/usr/bin/env python3
"""Where a learned policy's collecting (or driving) time goes, episode by episode, beside Lama's.

Flies `skyherd-sim run` for Lama and for a model on the same episode seeds (test noise, as the
simulator's `run` applies it), keeps each episode's trace in a temporary folder, and prints:

* per episode: success, steps, the lower bound, the model's steps over Lama's;
* the ratio of mean times over the episodes both finish, the median per-episode ratio, and the
  same split into thirds by the lower bound (short, middle, long episodes);
* phases, averaged over episodes: the step at which half the targets are in the goal and all
  are, the herders' median distance to their nearest target, their mean ground speed, the first
  step at which the herders' median distance to their nearest target is under 20 m, and the
  share of steps in which every herder is over 40 m from its nearest target (holding off);
* how far behind a target the herders push from: whenever a herder's nearest target is
  outside the goal, within 80 m, and the herder is on its far side from the goal (the cosine
  between herder-to-target and target-to-goal above 0.8), that distance, as quartiles over
  all such herder-steps (eq 6's push falls with its square: 3 m/s, the cap, at about 14 m).

Standard library only. Usage (from the repository root, after a release build):

    scripts/where-time-goes.py --model models/mtddpg-scratch.skym --task collecting \
        --targets 4 --herders 4 --episodes 40 --seed-base 3900000000
"""
import argparse
import json
import math
import os
import statistics as st
import subprocess
import sys
import tempfile

SCENARIO = {"collecting": "paper-collect", "driving": "paper-drive"}


def fly(sim, scenario, policy, seed, targets, herders, trace):
    """One episode: the summary `skyherd-sim run` prints, its trace written to `trace`."""
    try:
        out = subprocess.run(
            [sim, "run", "--scenario", scenario, "--policy", policy, "--seed", str(seed),
             "--targets", str(targets), "--herders", str(herders), "--out", trace],
            capture_output=True, text=True)
    except OSError as e:
        sys.exit(f"cannot run {sim}: {e} (build it with `cargo build --release -p skyherd-sim`)")
    if out.returncode != 0:
        # The first line is the error; a backtrace may follow when RUST_BACKTRACE is set.
        first = (out.stderr.strip().splitlines() or ["no message"])[0]
        sys.exit(f"{sim} run --policy {policy} --seed {seed} failed: {first}")
    return json.loads(out.stdout)


def phases(trace):
    """Half in, all in, median herder-to-nearest-target distance, mean speed, first close, held off."""
    worlds = []
    with open(trace) as f:
        for line in f:
            row = json.loads(line)
            if "world" in row:
                worlds.append(row["world"])
    goal = worlds[0]["goal"]
    centre, radius = goal["center"], goal["radius"]
    half = all_in = first_close = None
    nearest_medians, speeds, held_off, behind = [], [], 0, []
    previous = None
    for w in worlds:
        targets, herders = w["targets"], w["herders"]
        inside = sum(1 for t in targets if math.dist(t, centre) <= radius)
        if half is None and 2 * inside >= len(targets):
            half = w["step"]
        if all_in is None and inside == len(targets):
            all_in = w["step"]
        # Each herder's nearest target and its distance, found once for both measures.
        closest = [min((math.dist(h[:2], t), t) for t in targets) for h in herders]
        nearest = [d for d, _ in closest]
        for h, (d, t) in zip(herders, closest):
            if d > 80.0 or math.dist(t, centre) <= radius:
                continue
            push = (t[0] - h[0], t[1] - h[1])
            home = (centre[0] - t[0], centre[1] - t[1])
            norm = math.hypot(*push) * math.hypot(*home)
            if norm > 0 and (push[0] * home[0] + push[1] * home[1]) / norm > 0.8:
                behind.append(d)
        nearest_medians.append(st.median(nearest))
        if first_close is None and st.median(nearest) < 20.0:
            first_close = w["step"]
        if inside < len(targets) and min(nearest) > 40.0:
            held_off += 1
        if previous is not None:
            speeds.append(st.mean(math.dist(a[:2], b[:2]) for a, b in zip(herders, previous)))
        previous = herders
    return {
        "half_in": half,
        "all_in": all_in,
        "nearest_m": st.median(nearest_medians),
        "speed": st.mean(speeds) if speeds else 0.0,
        "first_close": first_close,
        "held_off": held_off / max(1, len(worlds)),
        "behind": behind,
    }


def mean_of(rows, key):
    values = [r[key] for r in rows if r[key] is not None]
    return (st.mean(values), len(values)) if values else (float("nan"), 0)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", required=True, help="a quantized model file (.skym)")
    ap.add_argument("--task", choices=sorted(SCENARIO), default="collecting")
    ap.add_argument("--targets", type=int, default=4)
    ap.add_argument("--herders", type=int, default=4)
    ap.add_argument("--episodes", type=int, default=40)
    ap.add_argument("--seed-base", type=int, default=3_900_000_000)
    ap.add_argument("--sim", default="target/release/skyherd-sim")
    args = ap.parse_args()
    if args.episodes < 3:
        sys.exit("--episodes must be at least 3 (the split is into thirds)")
    if not os.path.exists(args.model):
        sys.exit(f"no model file at {args.model}")
    scenario = SCENARIO[args.task]
    policies = {"lama": "lama", "model": f"model:{args.model}"}
    per_policy = {name: [] for name in policies}
    episodes = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.episodes):
            seed = args.seed_base + k
            row = {"seed": seed}
            for name, policy in policies.items():
                trace = os.path.join(tmp, f"{name}-{k}.jsonl")
                summary = fly(args.sim, scenario, policy, seed, args.targets, args.herders, trace)
                row[name] = summary
                if summary["success"]:
                    per_policy[name].append(phases(trace))
            episodes.append(row)
    print(f"{args.task}, N = {args.targets}, M = {args.herders}, {args.episodes} episodes "
          f"from seed {args.seed_base}, model {args.model}")
    print("| seed | Lama | model | bound (s) | model / Lama |")
    print("|---|---|---|---|---|")
    both = []
    for row in episodes:
        lama, model = row["lama"], row["model"]
        cell = lambda s: f"{s['steps']} steps" if s["success"] else "failed"
        ratio = "-"
        if lama["success"] and model["success"]:
            ratio = f"{model['steps'] / lama['steps']:.2f}"
            both.append((lama["lower_bound_s"], lama["steps"], model["steps"]))
        print(f"| {row['seed']} | {cell(lama)} | {cell(model)} | {lama['lower_bound_s']:.0f} | {ratio} |")
    if not both:
        print("no episode that both finish")
        return
    ratios = [m / l for _, l, m in both]
    print()
    print(f"both finish {len(both)} of {args.episodes}: mean time ratio "
          f"{st.mean(m for _, _, m in both) / st.mean(l for _, l, _ in both):.2f}, "
          f"median per-episode ratio {st.median(ratios):.2f}, "
          f"over 1.25x in {sum(r > 1.25 for r in ratios)} of {len(ratios)}")
    both.sort()
    third = len(both) / 3
    print("| episodes by lower bound | n | Lama / bound | model / bound | model / Lama |")
    print("|---|---|---|---|---|")
    for i, label in enumerate(["shortest third", "middle third", "longest third"]):
        part = both[round(i * third):round((i + 1) * third)]
        bound = st.mean(b for b, _, _ in part)
        lama = st.mean(l for _, l, _ in part)
        model = st.mean(m for _, _, m in part)
        print(f"| {label} ({part[0][0]:.0f}-{part[-1][0]:.0f} s) | {len(part)} | "
              f"{lama / bound:.2f} | {model / bound:.2f} | {model / lama:.2f} |")
    print()
    print("| policy | half in (step) | all in (step) | herder to nearest target (median, m) "
          "| herder speed (m/s) | herders' median under 20 m from (step) | steps held off (all > 40 m) |")
    print("|---|---|---|---|---|---|---|")
    for name, rows in per_policy.items():
        cells = []
        for key, fmt in [("half_in", "{:.0f}"), ("all_in", "{:.0f}"), ("nearest_m", "{:.0f}"),
                         ("speed", "{:.1f}"), ("first_close", "{:.0f}")]:
            value, n = mean_of(rows, key)
            cells.append(fmt.format(value) + ("" if n == len(rows) else f" ({n} of {len(rows)})"))
        value, _ = mean_of(rows, "held_off")
        cells.append(f"{100 * value:.0f} %")
        print(f"| {name} | " + " | ".join(cells) + " |")
    print()
    print("| policy | herder-steps behind a target | distance behind it, quartiles (m) |")
    print("|---|---|---|")
    for name, rows in per_policy.items():
        pooled = [d for r in rows for d in r["behind"]]
        if len(pooled) < 4:
            print(f"| {name} | {len(pooled)} | - |")
            continue
        q = st.quantiles(pooled, n=4)
        print(f"| {name} | {len(pooled)} | {q[0]:.0f} / {q[1]:.0f} / {q[2]:.0f} |")


if __name__ == "__main__":
    main()
