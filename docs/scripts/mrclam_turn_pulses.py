#!/usr/bin/env python3
"""How faithfully the MRCLAM robots execute short turn commands (README, "Cooperative
results", 2026-12-04). Standard library only.

Reads the raw dataset (`RobotN_Odometry.dat`, `RobotN_Groundtruth.dat`). MRCLAM's odometry is
the commanded velocity; turns are commanded as pulses of a constant angular rate. A pulse is a
run of non-zero angular rate (gaps of at most 0.05 s bridged). For every *isolated* pulse (no
other pulse within 1 s before or after) it compares the commanded turn (the rate integrated
over the pulse) with the true heading change from 0.05 s before the pulse to 0.8 s after it
(the robots follow their commands ≈ 0.25 s late). Per robot it prints the number of such
pulses, the least-squares fit `true = k·commanded − sign(commanded)·L` (a gain and a loss per
command, what a calibration could correct), the RMS of `true − commanded` before and after that
fit, and the median ratio true / commanded by pulse length. Then it prints robot 5's first
seconds, where its dead-reckoned heading loses 0.12 rad before its first landmark.

usage: mrclam_turn_pulses.py DATASET_DIR   (e.g. ../shared/data/mrclam6)
"""
import bisect
import math
import statistics
import sys

root = sys.argv[1]


def table(path):
    rows = []
    with open(path) as f:
        for line in f:
            if line.startswith("#") or not line.strip():
                continue
            rows.append([float(x) for x in line.split()])
    return rows


def unwrapped_heading(gt):
    t, h, prev, off = [], [], None, 0.0
    for r in gt:
        if prev is not None:
            d = r[3] - prev
            off -= 2 * math.pi * round(d / (2 * math.pi))
        prev = r[3]
        t.append(r[0])
        h.append(r[3] + off)
    return t, h


def interp(ts, vs, t):
    i = bisect.bisect_left(ts, t)
    if i <= 0:
        return vs[0]
    if i >= len(ts):
        return vs[-1]
    a = (t - ts[i - 1]) / (ts[i] - ts[i - 1])
    return vs[i - 1] + a * (vs[i] - vs[i - 1])


def commanded_turn(odo, a, b):
    """The commanded angular rate (zero-order hold, 0 before the first row) integrated over
    [a, b]."""
    acc = 0.0
    for m, r in enumerate(odo):
        nxt = odo[m + 1][0] if m + 1 < len(odo) else math.inf
        lo, hi = max(r[0], a), min(nxt, b)
        if hi > lo:
            acc += r[2] * (hi - lo)
    return acc


def pulses(odo):
    out, i, n = [], 0, len(odo)
    while i < n:
        if odo[i][2] == 0.0:
            i += 1
            continue
        j = i
        while True:
            k = j + 1
            while k < n and odo[k][2] == 0.0 and odo[k][0] - odo[j][0] <= 0.05:
                k += 1
            if k < n and odo[k][2] != 0.0 and odo[k][0] - odo[j][0] <= 0.05:
                j = k
                continue
            break
        end = odo[j + 1][0] if j + 1 < n else odo[j][0]
        out.append((odo[i][0], end, commanded_turn(odo[i:j + 2], odo[i][0], end)))
        i = j + 1
    return out


def fit_gain_loss(rows):
    # least squares of act = k·cmd − s·L, s = sign(cmd): 2×2 normal equations
    a11 = sum(c * c for _, c, _ in rows)
    a12 = sum(-abs(c) for _, c, _ in rows)
    a22 = float(len(rows))
    b1 = sum(c * a for _, c, a in rows)
    b2 = sum(-math.copysign(1.0, c) * a for _, c, a in rows)
    det = a11 * a22 - a12 * a12
    return (b1 * a22 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det


for robot in range(1, 6):
    odo = table(f"{root}/Robot{robot}_Odometry.dat")
    gt = table(f"{root}/Robot{robot}_Groundtruth.dat")
    ts, hs = unwrapped_heading(gt)
    ps = pulses(odo)
    rows = []
    for n, (s, e, cmd) in enumerate(ps):
        nxt = ps[n + 1][0] if n + 1 < len(ps) else math.inf
        prv = ps[n - 1][1] if n > 0 else -math.inf
        if nxt - e < 1.0 or s - prv < 1.0 or s < ts[0] or e + 1.0 > ts[-1]:
            continue
        act = interp(ts, hs, e + 0.8) - interp(ts, hs, s - 0.05)
        rows.append((e - s, cmd, act))
    k, loss = fit_gain_loss(rows)
    raw = math.sqrt(sum((a - c) ** 2 for _, c, a in rows) / len(rows))
    fitted = math.sqrt(sum((a - (k * c - math.copysign(loss, c))) ** 2
                           for _, c, a in rows) / len(rows))
    print(f"robot {robot}: {len(rows)} isolated turn commands of {len(ps)}; "
          f"fit gain {k:.3f}, loss {loss:+.4f} rad; RMS true - commanded {raw:.4f} rad, "
          f"after the fit {fitted:.4f} rad")
    for lo, hi in [(0.0, 0.2), (0.2, 0.4), (0.4, 0.8), (0.8, math.inf)]:
        sel = [(c, a) for d, c, a in rows if lo <= d < hi]
        if len(sel) >= 3:
            print(f"   commands {lo}-{hi} s long: {len(sel):3d}, median |commanded| "
                  f"{statistics.median(abs(c) for c, _ in sel):.3f} rad, "
                  f"median true/commanded {statistics.median(a / c for c, a in sel):.2f}")

odo = table(f"{root}/Robot5_Odometry.dat")
gt = table(f"{root}/Robot5_Groundtruth.dat")
ts, hs = unwrapped_heading(gt)
t0 = max(odo[0][0], gt[0][0])
print("robot 5, first seconds: time (s), commanded turn so far, true turn so far (rad)")
for horizon in [4.0, 5.0, 6.0, 6.5, 8.0, 10.0]:
    cmd = commanded_turn(odo, t0, t0 + horizon)
    true = interp(ts, hs, t0 + horizon) - interp(ts, hs, t0)
    print(f"   {horizon:4.1f}  {cmd:+.3f}  {true:+.3f}  (odometry off by {true - cmd:+.3f})")
