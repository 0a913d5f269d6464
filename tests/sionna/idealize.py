"""The ceiling of a perfect radio model: a ray-traced walk whose every track is replaced by a
point virtual transmitter, exactly as the filter models one.

Per track of at least two detections, a 2D virtual transmitter (x, y, b ≥ 0) is fitted by least
squares to its detections from the true poses (several starts along the first detection's ray,
the best kept). Each detection is then redrawn from that transmitter: d = |p − x| + b and the
angle of arrival relative to the true heading, plus white Gaussian noise at the walk's stated
noise law (σ_d = √(0.1² + (1.65/√(2·SNR))²) m, σ_θ = √(0.035² + (0.35/√(2·SNR))²) rad), which the
header's sensor profile states, with no gross errors. Tracks of one detection are dropped;
odometry, track ids, SNRs and truth stay as they are. A filter that is worse than dead reckoning
on such a log fails on its own terms, not on model misfit.

usage: idealize.py SRC_DIR DST_DIR SEED   (needs numpy and scipy)
"""

import collections
import json
import os
import shutil
import sys

import numpy as np
from scipy.optimize import least_squares

FLOOR_D, AT_0DB_D = 0.1, 1.65 / 2**0.5
FLOOR_A, AT_0DB_A = 0.035, 0.35 / 2**0.5


def wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def main(src, dst, seed):
    rng = np.random.default_rng(seed)
    os.makedirs(dst, exist_ok=True)
    shutil.copy(os.path.join(src, "truth.json"), dst)
    lines = open(os.path.join(src, "log.jsonl")).read().splitlines()
    head = json.loads(lines[0])
    snaps = [json.loads(l) for l in lines[1:]]
    poses = json.load(open(os.path.join(src, "truth.json")))["poses"]
    tracks = collections.defaultdict(list)
    for k, s in enumerate(snaps):
        for j, c in enumerate(s["components"]):
            tracks[c["track"]].append((k, j))
    model = {}
    at_bound = 0
    for obs in tracks.values():
        if len(obs) < 2:
            continue
        ks = np.array([k for k, _ in obs])
        d = np.array([snaps[k]["components"][j]["d"] for k, j in obs])
        a = np.array([snaps[k]["components"][j]["aoa"] for k, j in obs])
        x = np.array([poses[k]["x"] for k in ks])
        y = np.array([poses[k]["y"] for k in ks])
        h = np.array([poses[k]["heading_rad"] for k in ks])

        def residuals(p):
            r = np.hypot(p[0] - x, p[1] - y)
            return np.concatenate(
                [(r + p[2] - d) / FLOOR_D, wrap(np.arctan2(p[1] - y, p[0] - x) - h - a) / FLOOR_A]
            )

        best = None
        for frac in (0.0, 0.3, 0.6, 0.9):
            r0 = d[0] * (1 - frac)
            start = [x[0] + r0 * np.cos(h[0] + a[0]), y[0] + r0 * np.sin(h[0] + a[0]), max(d[0] * frac, 1e-6)]
            fit = least_squares(residuals, start, bounds=([-np.inf, -np.inf, 0.0], [np.inf, np.inf, np.inf]))
            if best is None or fit.cost < best.cost:
                best = fit
        p = best.x
        at_bound += p[2] < 1e-6
        for k, j in obs:
            px, py = poses[k]["x"], poses[k]["y"]
            model[(k, j)] = (
                np.hypot(p[0] - px, p[1] - py) + p[2],
                wrap(np.arctan2(p[1] - py, p[0] - px) - poses[k]["heading_rad"]),
            )
    head["sensor"] = {
        "name": "idealized point transmitters (tests/sionna/idealize.py)",
        "distance_m": {"floor": FLOOR_D, "at_0db": AT_0DB_D},
        "aoa_rad": {"floor": FLOOR_A, "at_0db": AT_0DB_A},
        "outlier_probability": 0.0,
    }
    with open(os.path.join(dst, "log.jsonl"), "w") as out:
        out.write(json.dumps(head) + "\n")
        for k, s in enumerate(snaps):
            comps = []
            for j, c in enumerate(s["components"]):
                if (k, j) not in model:
                    continue
                f = 10 ** (-c["snr_db"] / 20)
                dm, am = model[(k, j)]
                c = dict(c)
                c["d"] = float(dm + rng.normal(0, np.hypot(FLOOR_D, AT_0DB_D * f)))
                c["aoa"] = float(wrap(am + rng.normal(0, np.hypot(FLOOR_A, AT_0DB_A * f))))
                comps.append(c)
            s = dict(s)
            s["components"] = comps
            out.write(json.dumps(s) + "\n")
    fitted = sum(1 for o in tracks.values() if len(o) >= 2)
    print(f"{dst}: {fitted} tracks as point transmitters ({at_bound} at b = 0), {len(tracks) - fitted} single detections dropped")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]))
