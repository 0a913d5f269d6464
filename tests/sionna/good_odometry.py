"""A ray-traced walk with an almost perfect odometry: the log's gyro and speed replaced by the
true heading rate and speed (from truth.json) plus only the white noise of the original
(0.005 rad/s·sqrt(10 Hz), 0.05 m/s) — no gyro bias, no speed scale error. The radio must not make
such a walk worse than its dead reckoning.

    python3 tests/sionna/good_odometry.py ../shared/data/sionna/etoile-walk1 OUT_DIR SEED
"""
import json, math, random, sys, os, shutil
src, dst, seed = sys.argv[1], sys.argv[2], int(sys.argv[3])
rng = random.Random(seed)
os.makedirs(dst, exist_ok=True)
shutil.copy(os.path.join(src, 'truth.json'), dst)
truth = json.load(open(os.path.join(src, 'truth.json')))
poses = truth['poses']
out = open(os.path.join(dst, 'log.jsonl'), 'w')
for i, line in enumerate(open(os.path.join(src, 'log.jsonl'))):
    rec = json.loads(line)
    if i == 0:
        out.write(line); continue
    k = i - 1
    if 'gyro' in rec:
        if k == 0:
            g = 0.0
        else:
            dh = poses[k]['heading_rad'] - poses[k-1]['heading_rad']
            dh = math.atan2(math.sin(dh), math.cos(dh))
            g = dh / (poses[k]['t'] - poses[k-1]['t'])
        rec['gyro'] = g + rng.gauss(0, 0.005 * math.sqrt(10))
        rec['speed'] = poses[k]['speed_mps'] + rng.gauss(0, 0.05)
    out.write(json.dumps(rec) + '\n')
