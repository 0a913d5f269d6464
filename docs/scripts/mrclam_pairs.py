#!/usr/bin/env python3
"""Pairwise map matching on MRCLAM against the truth (docs/results/cooperative.md, "Cooperative Channel-SLAM").

Takes the output directory of `echomap-agent experiment cooperative --dataset mrclam ...`:
every run directory `robotR/run-seedS/` holds the maps the four contributors uploaded
(`robotN/map.json`, each in its robot's local frame) and `logs/robotN/truth.json` holds
`world_from_local` of every robot. Every ordered pair of contributor maps of a run is matched
with `echomap-agent match USER PRIOR --seed 7 --json [extra flags]` and the returned
`map_from_agent` compared with the true relation of the two local frames,
world_from_local(PRIOR)^-1 * world_from_local(USER).

A match counts as right when its rotation is within 0.7 rad of the truth (single-user maps are
themselves rotated by up to ~0.5 rad against their true local frame: the heading drift before
the landmarks pin it) and as a half turn when it is more than 2 rad off.

usage: mrclam_pairs.py EXPERIMENT_DIR ECHOMAP_AGENT [extra match flags, e.g. --visibility-weight 0 --score likelihood]
"""
import glob
import json
import math
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

root, exe, extra = sys.argv[1], sys.argv[2], sys.argv[3:]


def world_from_local(robot):
    with open(f"{root}/logs/robot{robot}/truth.json") as f:
        w = json.load(f)["world_from_local"]
    return w["angle_rad"]


def jobs():
    for run in sorted(glob.glob(f"{root}/robot*/run-seed*")):
        maps = {}
        for d in glob.glob(f"{run}/robot[0-9]"):
            if os.path.exists(f"{d}/map.json"):
                maps[int(os.path.basename(d)[5:])] = f"{d}/map.json"
        for u in maps:
            for p in maps:
                if u != p:
                    yield u, p, maps[u], maps[p]


def match(job):
    u, p, user, prior = job
    out = subprocess.run(
        [exe, "match", user, prior, "--json", "--seed", "7", *extra],
        capture_output=True, text=True, check=True,
    ).stdout
    r = json.loads(out)
    truth = world_from_local(u) - world_from_local(p)
    err = abs(math.remainder(r["map_from_agent"]["angle_rad"] - truth, 2 * math.pi))
    return r["accepted"], err


with ThreadPoolExecutor(2) as ex:
    results = list(ex.map(match, jobs()))
accepted = [e for ok, e in results if ok]
right = sum(e < 0.7 for e in accepted)
half = sum(e > 2.0 for e in accepted)
print(f"pairs {len(results)}, accepted {len(accepted)}: right {right}, "
      f"wrong {len(accepted) - right} (half turns {half})")
