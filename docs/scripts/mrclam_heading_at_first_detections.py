#!/usr/bin/env python3
"""How far each MRCLAM robot's dead-reckoned heading is off when it first sees landmarks (docs/results/cooperative.md,
"Cooperative Channel-SLAM", 2026-12-04). Standard library only.

Takes the output directory of `echomap-agent experiment cooperative --dataset mrclam ...` (its
imported `logs/robotN/log.jsonl` and `truth.json`). Per robot it integrates the log's gyro alone
from the known start heading and prints, for the first six tracks (landmarks) the robot detects,
the time of the first detection and the dead-reckoned heading's error then (rad, odometry minus
truth). No estimator can know the relation of the robot's local frame to a prior map better than
the pose it had when it first saw that map's landmarks: a frame turned by δ about the start puts a
pose at distance r from it 2·|sin(δ/2)|·r off. The last column is that error averaged over the
true track for δ the error at the third landmark — what a transform fixed then would add.

usage: mrclam_heading_at_first_detections.py EXPERIMENT_DIR
"""
import json
import math
import sys

root = sys.argv[1]


def wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


print("robot | mean distance from the start (m) | first tracks: t (s) / heading error (rad) "
      "| error for the 3rd's heading error (m)")
for robot in range(1, 6):
    with open(f"{root}/logs/robot{robot}/log.jsonl") as f:
        snaps = [json.loads(line) for line in f][1:]
    with open(f"{root}/logs/robot{robot}/truth.json") as f:
        poses = json.load(f)["poses"]
    truth = {round(p["t"], 1): p for p in poses}
    dist = sum(math.hypot(p["x"], p["y"]) for p in poses) / len(poses)
    h, prev, first = 0.0, None, {}
    for s in snaps:
        if prev is not None:
            h += s["gyro"] * (s["t"] - prev)
        prev = s["t"]
        pose = truth.get(round(s["t"], 1))
        for c in s["components"]:
            if c["track"] not in first and pose is not None:
                first[c["track"]] = (s["t"], wrap(h - pose["heading_rad"]))
    order = sorted(first.values())[:6]
    floor = 2 * abs(math.sin(order[2][1] / 2)) * dist if len(order) > 2 else float("nan")
    print(f"{robot} | {dist:.2f} | {' '.join(f'{t:.1f}/{e:+.2f}' for t, e in order)} | {floor:.2f}")
