#!/usr/bin/env python3
"""The ceiling of the MRCLAM cooperative experiment (docs/results/cooperative.md): each
reference robot run alone and with the *true* landmark map as its prior, under the experiment's
own protocol (the log's sensor profile and the `mrclam` preset, matched into the robot's frame
by the agent).
Standard library only; needs release binaries (`cargo build --release`).

The true map is the 15 landmarks of the robot's `truth.json` (the importer's ground truth, in
the robot's local frame), moved by a fixed rigid transform (1 rad, (2, -1) m) so that the agent
has to match it like a crowd map, every landmark one Gaussian of std 0.1 m (the experiment's
`prior.position_floor_m = 0.15` is added by the agent), existence 1, reliability 50 m, no visibility.

A run whose directory already holds its summary.json is not run again, so an interrupted call
resumes. Writes OUT_DIR/summary.json in the experiment's layout (labels `robotN-alone` and
`robotN-with-others`, here "with the true map"), so that
`cargo run --release --example paired_stats -- OUT_DIR` prints the paired table: per robot and
measure (mean MAE, final MAE, ATE) the median of with - alone over the seeds, the runs lower
with the map, and the exact two-sided Wilcoxon signed-rank p.

usage: mrclam_true_map_prior.py DATASET_DIR OUT_DIR [--robots 1,2,3,4,5] [--seeds 1-40]
       [--jobs 2] [-- EXTRA_RUN_FLAGS...]
"""
import concurrent.futures
import json
import math
import os
import subprocess
import sys

EXE = os.path.join(os.path.dirname(__file__), "../../target/release/echomap-agent")
# the imported log's sensor profile sets the filter; the `mrclam` preset how the prior is used
FLAGS = "--particles 500 --preset mrclam".split()


def true_map(truth_path, out_path, angle=1.0, tx=2.0, ty=-1.0, std=0.1):
    with open(truth_path) as f:
        truth = json.load(f)
    landmarks = sorted({(round(t["state"][0], 6), round(t["state"][1], 6)) for t in truth["transmitters"]})
    c, s = math.cos(angle), math.sin(angle)
    txs = [
        {
            "id": f"lm{i}",
            "components": [
                {
                    "weight": 1.0,
                    "mean": [c * x - s * y + tx, s * x + c * y + ty, 0.0],
                    "cov": [[std * std, 0, 0], [0, std * std, 0], [0, 0, 1e-4]],
                }
            ],
            "existence": 1.0,
            "reliability_m": 50.0,
            "visibility": [],
        }
        for i, (x, y) in enumerate(landmarks)
    ]
    with open(out_path, "w") as f:
        json.dump({"format": "echomap.map.v1", "hex_size_m": 2.0, "transmitters": txs}, f)
    return len(txs)


def run(args):
    out = args[args.index("--out") + 1]
    if os.path.exists(f"{out}/summary.json"):
        return  # done by an earlier, interrupted call
    subprocess.run([EXE, "run", *args], check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def main():
    argv = sys.argv[1:]
    extra = []
    if "--" in argv:
        i = argv.index("--")
        argv, extra = argv[:i], argv[i + 1 :]
    opts = {"--robots": "1,2,3,4,5", "--seeds": "1-40", "--jobs": "2"}
    pos = []
    while argv:
        a = argv.pop(0)
        if a in opts:
            opts[a] = argv.pop(0)
        else:
            pos.append(a)
    dataset, out = pos
    robots = [int(r) for r in opts["--robots"].split(",")]
    lo, hi = map(int, opts["--seeds"].split("-"))
    seeds = range(lo, hi + 1)
    jobs = []
    for r in robots:
        logs = f"{out}/logs/robot{r}"
        if not os.path.exists(f"{logs}/log.jsonl"):
            subprocess.run([EXE, "import", "mrclam", dataset, "--robot", str(r), "--out", logs], check=True, stdout=subprocess.DEVNULL)
        prior = f"{out}/true-map-robot{r}.json"
        n = true_map(f"{logs}/truth.json", prior)
        assert n == 15, f"robot {r}: {n} landmarks in truth.json"
        for s in seeds:
            base = ["--log", logs, "--seed", str(s), "--quiet", *FLAGS]
            jobs.append(base + ["--out", f"{out}/robot{r}/alone-{s}", *extra])
            jobs.append(base + ["--out", f"{out}/robot{r}/true-map-{s}", "--prior", prior, *extra])
    with concurrent.futures.ThreadPoolExecutor(int(opts["--jobs"])) as pool:
        list(pool.map(run, jobs))
    curves = []
    for r in robots:
        for label, name in [("alone", "alone"), ("true-map", "with-others")]:
            runs = []
            for s in seeds:
                with open(f"{out}/robot{r}/{label}-{s}/summary.json") as f:
                    runs.append(json.load(f))
            curves.append(
                {
                    "label": f"robot{r}-{name}",
                    **{k: [] for k in ["traveled_m", "mae_mean", "mae_p5", "mae_p95", "rmse", "wall_s"]},
                    "final_mae": [x["mae_final_m"] for x in runs],
                    "mean_mae": [x["mae_mean_m"] for x in runs],
                    "ate_m": [x["ate_m"] for x in runs],
                }
            )
    with open(f"{out}/summary.json", "w") as f:
        json.dump(curves, f)
    print(f"wrote {out}/summary.json; cargo run --release --example paired_stats -- {out}")

if __name__ == "__main__":
    main()
