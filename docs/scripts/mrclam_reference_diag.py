#!/usr/bin/env python3
"""Why a MRCLAM reference robot gains or loses with the others' map (docs/results/cooperative.md, "Cooperative
Channel-SLAM", 2026-12-03). Standard library only.

Takes the output directory of `echomap-agent experiment cooperative --dataset mrclam ...` and a
reference robot R. Per run `robotR/run-seedS/` it prints:
- the reference's mean MAE alone and with the others' map (`summary.json`);
- the *shape* error of every map: the median distance from each transmitter mean (existence
  >= 0.5, mixture mean) to the nearest true landmark after the best rigid fit of the map to the
  landmarks (ICP from 12 start angles) — R's own map alone, each contributor's upload, and the
  crowd map R received (`prior.json`, in the first contributor's frame); for the crowd also a
  trimmed fit (the closest 60 % of pairs), which a few far-off transmitters cannot pull: its
  median and the share of the crowd's transmitters within 0.3 m of a landmark;
- the *frame* error of R's own map: the same median without the fit (R's true local frame);
- the prior matches R adopted (`prior_matches.csv`, actions adopted/replaced): the time of the
  first, and for the first and the last the rotation (rad) and the displacement at the
  landmarks' centroid (m) against the right transform — the true relation of R's local frame
  to the crowd's frame, the latter fitted to the first contributor's landmarks.

usage: mrclam_reference_diag.py EXPERIMENT_DIR R
"""
import csv
import glob
import json
import math
import sys

root, ref = sys.argv[1], int(sys.argv[2])


def truth(robot):
    with open(f"{root}/logs/robot{robot}/truth.json") as f:
        return json.load(f)


def landmarks(robot):
    return [tuple(t["state"][:2]) for t in truth(robot)["transmitters"]]


def means(path):
    with open(path) as f:
        m = json.load(f)
    out = []
    for tx in m["transmitters"]:
        if tx.get("existence", 1.0) < 0.5:
            continue
        w = sum(c["weight"] for c in tx["components"])
        x = sum(c["weight"] * c["mean"][0] for c in tx["components"]) / w
        y = sum(c["weight"] * c["mean"][1] for c in tx["components"]) / w
        out.append((x, y))
    return out


def apply(tf, p):
    a, tx, ty = tf
    c, s = math.cos(a), math.sin(a)
    return (c * p[0] - s * p[1] + tx, s * p[0] + c * p[1] + ty)


def compose(f, g):
    """f after g."""
    tx, ty = apply(f, (g[1], g[2]))
    return (f[0] + g[0], tx, ty)


def inverse(f):
    a = -f[0]
    c, s = math.cos(a), math.sin(a)
    return (a, -(c * f[1] - s * f[2]), -(s * f[1] + c * f[2]))


def nearest(p, pts):
    return min(pts, key=lambda q: (q[0] - p[0]) ** 2 + (q[1] - p[1]) ** 2)


def median(v):
    v = sorted(v)
    n = len(v)
    return (v[n // 2] + v[(n - 1) // 2]) / 2


def median_nn(pts, targets):
    return median([math.dist(p, nearest(p, targets)) for p in pts])


def rigid(src, dst):
    """Least-squares rigid transform taking src onto dst (paired)."""
    n = len(src)
    cs = (sum(p[0] for p in src) / n, sum(p[1] for p in src) / n)
    cd = (sum(p[0] for p in dst) / n, sum(p[1] for p in dst) / n)
    sxx = sum((p[0] - cs[0]) * (q[0] - cd[0]) + (p[1] - cs[1]) * (q[1] - cd[1]) for p, q in zip(src, dst))
    sxy = sum((p[0] - cs[0]) * (q[1] - cd[1]) - (p[1] - cs[1]) * (q[0] - cd[0]) for p, q in zip(src, dst))
    a = math.atan2(sxy, sxx)
    c, s = math.cos(a), math.sin(a)
    return (a, cd[0] - (c * cs[0] - s * cs[1]), cd[1] - (s * cs[0] + c * cs[1]))


def fit_from_angles(src, dst, passes, keep=1.0):
    """ICP of src onto dst from 12 start angles; after 5 full passes each fit uses only the
    closest `keep` share of the pairs. The best start's (median error, transform, distances)."""
    best = None
    cd = (sum(p[0] for p in dst) / len(dst), sum(p[1] for p in dst) / len(dst))
    cs = (sum(p[0] for p in src) / len(src), sum(p[1] for p in src) / len(src))
    for k in range(12):
        a = 2 * math.pi * k / 12
        r = apply((a, 0.0, 0.0), cs)
        tf = (a, cd[0] - r[0], cd[1] - r[1])
        for it in range(passes):
            moved = [apply(tf, p) for p in src]
            pairs = [(math.dist(m, nearest(m, dst)), p, nearest(m, dst)) for m, p in zip(moved, src)]
            if keep < 1.0 and it >= 5:
                pairs = sorted(pairs, key=lambda x: x[0])[:max(3, int(len(pairs) * keep))]
            tf = rigid([q[1] for q in pairs], [q[2] for q in pairs])
        d = [math.dist(apply(tf, p), nearest(apply(tf, p), dst)) for p in src]
        e = median(d)
        if best is None or e < best[0]:
            best = (e, tf, d)
    return best


def icp(src, dst):
    """Best rigid fit of src onto dst (ICP from 12 start angles): (median error, transform)."""
    e, tf, _ = fit_from_angles(src, dst, 20)
    return e, tf


def icp_trimmed(src, dst, keep=0.6):
    """ICP as `icp`, but after 5 full passes each fit uses only the closest `keep` share of the
    pairs, so transmitters far from every landmark (a contributor's duplicates) do not pull
    the fit: (median error, share of transmitters within 0.3 m of a landmark)."""
    e, _, d = fit_from_angles(src, dst, 30, keep)
    return e, sum(1 for x in d if x < 0.3) / len(d)


def wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


def world_from_local(robot):
    w = truth(robot)["world_from_local"]
    return (w["angle_rad"], w["translation"][0], w["translation"][1])


first = [r for r in range(1, 6) if r != ref][0]
lm_ref, lm_first = landmarks(ref), landmarks(first)
centroid = (sum(p[0] for p in lm_ref) / len(lm_ref), sum(p[1] for p in lm_ref) / len(lm_ref))
# true relation of R's local frame to the first contributor's local frame
first_from_ref = compose(inverse(world_from_local(first)), world_from_local(ref))

print("seed | mean MAE alone -> with | own map frame / shape | contributors' shapes | crowd shape "
      "| crowd core (trimmed fit): median, share within 0.3 m "
      "| first match t | first / last adopted transform: rotation (rad), displacement (m)")
for run in sorted(glob.glob(f"{root}/robot{ref}/run-seed*"), key=lambda s: int(s.rsplit("seed", 1)[1])):
    seed = int(run.rsplit("seed", 1)[1])
    try:
        alone = json.load(open(f"{run}/reference-alone/summary.json"))["mae_mean_m"]
        withm = json.load(open(f"{run}/reference-with-others/summary.json"))["mae_mean_m"]
    except FileNotFoundError:
        continue
    own = means(f"{run}/reference-alone/map.json")
    shapes = []
    for r in range(1, 6):
        if r != ref:
            shapes.append(f"r{r} {icp(means(f'{run}/robot{r}/map.json'), landmarks(r))[0]:.2f}")
    crowd = means(f"{run}/prior.json")
    crowd_err, first_from_crowd = icp(crowd, lm_first)
    core, share = icp_trimmed(crowd, lm_first)
    right = compose(inverse(first_from_crowd), first_from_ref)  # crowd-frame from R's true frame
    rows = [r for r in csv.DictReader(open(f"{run}/reference-with-others/prior_matches.csv"))
            if r["action"] in ("adopted", "replaced")]

    def offset(r):
        tf = (float(r["angle_rad"]), float(r["tx"]), float(r["ty"]))
        return wrap(tf[0] - right[0]), math.dist(apply(tf, centroid), apply(right, centroid))

    used = "-"
    if rows:
        (a0, d0), (a1, d1) = offset(rows[0]), offset(rows[-1])
        used = f"{rows[0]['t']} s | {a0:+.2f}, {d0:.2f} / {a1:+.2f}, {d1:.2f}"
    print(f"{seed} | {alone:.3f} -> {withm:.3f} | {median_nn(own, lm_ref):.2f} / {icp(own, lm_ref)[0]:.2f} "
          f"| {' '.join(shapes)} | {crowd_err:.2f} | {core:.2f}, {share:.0%} | {used}")
