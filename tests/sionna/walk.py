"""A walk through one of Sionna RT's built-in city scenes, ray-traced, written as an echomap
measurement log (`echomap.log.v1`) with its ground truth (`echomap.truth.v1`).

    python3 tests/sionna/walk.py --scene munich --seed 1 --out OUT_DIR
    python3 tests/sionna/walk.py --scene simple_street_canyon --seed 1 --cir --out OUT_DIR

Needs `pip install -r tests/sionna/requirements.txt` and, on a CPU-only machine, LLVM for
Dr.Jit (Debian: `apt-get install libllvm19`, then
`export DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM-19.so`).

What it makes (the same recipe as the ray-traced walks echomap is measured on):
- The walk: a closed loop around one block, on the line 6 m from the nearest building (a
  contour of the street clearance), 300–500 m long, at 5 m/s, 10 snapshots/s. The loop and
  the transmitter are drawn from `--layout`, the start point, direction and noise from
  `--seed`: walks with one layout and several seeds are a crowd on the same streets.
- One transmitter 3 m above the ground in a street (≥ 3 m from buildings) 8–30 m from the loop;
  the receiver 1.5 m above the ground. 1.5 GHz, 100 MHz, isotropic antennas, 30 dBm transmit
  power, noise −174 dBm/Hz with a 7 dB noise figure.
- Paths: line of sight, specular reflections up to third order and edge diffraction (no
  diffuse scattering, no refraction).
- Resolution: of two paths closer than c/B = 3 m in distance and 0.35 rad in angle only the
  stronger is kept; a path is detected when its SNR is ≥ 3 dB.
- Track ids as a KEST-style tracker gives them: a path continues the track of the previous
  snapshot's path with the same interaction sequence (kinds and objects), else of the nearest
  previous path within 0.6 m and 0.08 rad; otherwise it starts a new id.
- Noise: σ_d = √(0.1² + (1.65/√(2·SNR))²) m, σ_θ = √(0.035² + (0.35/√(2·SNR))²) rad.
- Odometry: gyro = true heading rate + 0.003 rad/s bias + white noise 0.005 rad/s·√(10 Hz);
  speed = 1.02 × true speed + N(0, 0.05 m/s).
- With `--cir`, also the sampled channel as `echomap.cir.v1` (`cir.json` + `cir.npy`, the input
  of `echomap-agent estimate`): every traced path down to 30 dB below the detection threshold,
  with Sionna's complex gain (its carrier phase included), its delay and its direction of
  arrival in 3D — at a 3 × 3 square array of isotropic elements λ/2 apart in the horizontal
  plane, a path arriving at an elevation ε contributes the phase of its horizontal part only
  (cos ε) — band-limited by a sinc pulse of the bandwidth, sampled at the bandwidth, in complex
  white noise of unit variance per sample and element (per-sample SNR = the path's SNR over the
  band). Nothing is resolved or tracked: that is what `estimate` does.
- `truth.json`: poses in the local frame (start pose, +x along the initial heading) and the
  physical transmitter (track 0).
"""

import argparse
import json
import math
import os
import sys

import numpy as np

C = 299_792_458.0
RATE_HZ = 10.0
SPEED = 5.0
FREQUENCY = 1.5e9
BANDWIDTH = 100e6
TX_POWER_DBM = 30.0
NOISE_DBM = -174.0 + 10.0 * math.log10(BANDWIDTH) + 7.0
CLEARANCE_M = 6.0
RES_D_M = C / BANDWIDTH
RES_AOA_RAD = 0.35
DETECT_DB = 3.0


def wrap(a):
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def street_grid(scene, cell):
    """Ground height and clearance (m to the nearest building) on a grid over the scene."""
    import drjit as dr  # noqa: F401  (mitsuba needs it loaded)
    import mitsuba as mi
    from scipy import ndimage

    bb = scene.mi_scene.bbox()
    xs = np.arange(bb.min[0] + cell / 2, bb.max[0], cell)
    ys = np.arange(bb.min[1] + cell / 2, bb.max[1], cell)
    gx, gy = np.meshgrid(xs, ys)
    o = mi.Point3f(
        mi.Float(gx.ravel().astype(np.float32)),
        mi.Float(gy.ravel().astype(np.float32)),
        mi.Float(np.full(gx.size, bb.max[2] + 10.0, np.float32)),
    )
    si = scene.mi_scene.ray_intersect(mi.Ray3f(o, mi.Vector3f(0.0, 0.0, -1.0)))
    z = np.array(si.p.z).reshape(gx.shape)
    valid = np.array(si.is_valid()).reshape(gx.shape)
    ground = np.percentile(z[valid], 5)
    street = valid & (z < ground + 1.0)
    clearance = ndimage.distance_transform_edt(street) * cell
    return xs, ys, np.where(valid, z, np.nan), street, clearance


def closed_loops(xs, ys, clearance, lo, hi):
    """Closed contours of the clearance at CLEARANCE_M whose length is in [lo, hi]."""
    import contourpy

    gen = contourpy.contour_generator(xs, ys, clearance, line_type="Separate")
    loops = []
    for line in gen.lines(CLEARANCE_M):
        if len(line) < 10 or np.hypot(*(line[0] - line[-1])) > 1e-6:
            continue
        seg = np.hypot(*np.diff(line, axis=0).T)
        length = seg.sum()
        if lo <= length <= hi:
            loops.append(line)
    return loops


def resample_closed(line, step):
    """Points every `step` metres along a closed polyline, smoothed over ±4 m."""
    seg = np.hypot(*np.diff(line, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    total = s[-1]
    fine = np.arange(0.0, total, 0.25)
    px = np.interp(fine, s, line[:, 0])
    py = np.interp(fine, s, line[:, 1])
    k = 16  # ±4 m at 0.25 m
    ker = np.ones(2 * k + 1) / (2 * k + 1)
    px = np.convolve(np.concatenate([px[-k:], px, px[:k]]), ker, "valid")
    py = np.convolve(np.concatenate([py[-k:], py, py[:k]]), ker, "valid")
    seg = np.hypot(np.diff(np.append(px, px[0])), np.diff(np.append(py, py[0])))
    s = np.concatenate([[0.0], np.cumsum(seg)])
    total = s[-1]
    n = int(total // step)
    at = np.arange(n) * step
    return np.stack([np.interp(at, s, np.append(px, px[0])), np.interp(at, s, np.append(py, py[0]))], 1)


def inside(poly, p):
    x, y = p
    c = False
    n = len(poly)
    for i in range(n):
        (x1, y1), (x2, y2) = poly[i], poly[(i + 1) % n]
        if (y1 > y) != (y2 > y) and x < x1 + (y - y1) * (x2 - x1) / (y2 - y1):
            c = not c
    return c


def lookup(xs, ys, grid, x, y):
    i = int(np.clip(np.searchsorted(ys, y), 0, len(ys) - 1))
    j = int(np.clip(np.searchsorted(xs, x), 0, len(xs) - 1))
    return grid[i, j]


def plan(scene, layout, walk, cell, loop_m):
    """The loop and the transmitter (drawn by `layout`), the start and direction (by `walk`)."""
    xs, ys, z, street, clearance = street_grid(scene, cell)
    lo, hi = loop_m
    loops = closed_loops(xs, ys, clearance, lo, hi)
    if not loops:
        sys.exit(f"no closed loop of {lo:.0f}–{hi:.0f} m at 6 m from the buildings in this scene: try --loop-m")
    loop = loops[layout.integers(len(loops))]
    pts = resample_closed(loop, SPEED / RATE_HZ)
    clear = np.array([lookup(xs, ys, clearance, x, y) for x, y in pts])
    if clear.min() < 4.5:
        print(f"note: the smoothed loop comes {clear.min():.1f} m close to a building", file=sys.stderr)
    # the transmitter: a street cell 8–30 m from the loop, ≥ 3 m from buildings, outside the block
    gx, gy = np.meshgrid(xs, ys)
    cand = np.argwhere(clearance >= 3.0)
    layout.shuffle(cand)
    tx = None
    for i, j in cand[:200000]:
        p = np.array([gx[i, j], gy[i, j]])
        dist = np.hypot(*(pts - p).T).min()
        if 8.0 <= dist <= 30.0 and not inside(pts, p):
            tx = p
            break
    if tx is None:
        sys.exit("no street cell 8–30 m from the loop for the transmitter")
    pts = np.roll(pts, -walk.integers(len(pts)), axis=0)
    if walk.random() < 0.5:
        pts = pts[::-1]
    pts = np.vstack([pts, pts[:1]])  # back to the start
    return pts, tx, xs, ys, z


def trace(scene, pts, tx, xs, ys, z, batch, max_depth, seed):
    """Per snapshot, the paths: (delay distance, world azimuth of arrival, power, key)."""
    from sionna.rt import PathSolver, PlanarArray, Receiver, Transmitter

    scene.frequency = FREQUENCY
    scene.tx_array = PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    scene.rx_array = PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    tz = lookup(xs, ys, z, *tx) + 3.0
    scene.add(Transmitter("tx", position=[float(tx[0]), float(tx[1]), float(tz)]))
    solver = PathSolver()
    out = []
    for b0 in range(0, len(pts), batch):
        names = []
        for k in range(b0, min(b0 + batch, len(pts))):
            x, y = pts[k]
            rz = lookup(xs, ys, z, x, y) + 1.5
            names.append(f"rx{k}")
            scene.add(Receiver(names[-1], position=[float(x), float(y), float(rz)]))
        p = solver(
            scene,
            max_depth=max_depth,
            los=True,
            specular_reflection=True,
            diffuse_reflection=False,
            refraction=False,
            diffraction=True,
            synthetic_array=True,
            seed=seed,
        )
        ar, ai = p.a
        gain = np.array(ar) + 1j * np.array(ai)  # [rx, rx_ant, tx, tx_ant, path]
        amp2 = np.abs(gain) ** 2
        tau = np.array(p.tau)  # [rx, tx, path]
        phi = np.array(p.phi_r)
        zenith = np.array(p.theta_r)
        valid = np.array(p.valid)
        inter = np.array(p.interactions)  # [depth, rx, tx, path]
        objs = np.array(p.objects)
        prims = np.array(p.primitives)
        for r in range(len(names)):
            paths = []
            for q in range(tau.shape[-1]):
                if not valid[r, 0, q]:
                    continue
                pw = amp2[r, 0, 0, 0, q]
                if pw <= 0.0:
                    continue
                key = tuple(
                    int(v) for v in np.concatenate([inter[:, r, 0, q], objs[:, r, 0, q], prims[:, r, 0, q]])
                )
                paths.append(
                    (
                        float(tau[r, 0, q]) * C,
                        float(phi[r, 0, q]),
                        float(pw),
                        key,
                        complex(gain[r, 0, 0, 0, q]),
                        float(zenith[r, 0, q]),
                    )
                )
            out.append(paths)
        for n in names:
            scene.remove(n)
        print(f"  traced {min(b0 + batch, len(pts))}/{len(pts)} snapshots", file=sys.stderr)
    return out, tz


def write_cir(a, paths, heading, records):
    """The sampled channel of every snapshot at a 3 × 3 array (see the module's docstring)."""
    lam = C / FREQUENCY
    spacing = lam / 2.0
    elements = np.array([[(i - 1) * spacing, (j - 1) * spacing] for i in range(3) for j in range(3)])
    mps = C / BANDWIDTH
    longest = max((p[0] for snap in paths for p in snap), default=0.0)
    samples = int(math.ceil(longest / mps)) + 16
    k_wave = 2.0 * math.pi / lam
    n = np.arange(samples)
    weakest_db = DETECT_DB - 30.0
    y = np.zeros((len(paths), len(elements), samples), dtype=np.complex128)
    for k, snap in enumerate(paths):
        for d, phi, pw, _, g, zenith in snap:
            snr_db = TX_POWER_DBM + 10.0 * math.log10(pw) - NOISE_DBM
            if snr_db < weakest_db:
                continue
            amp = math.sqrt(10.0 ** (snr_db / 10.0)) * g / abs(g)
            az = phi - heading[k]
            horizontal = math.sin(zenith)  # cos of the elevation
            u = horizontal * np.array([math.cos(az), math.sin(az)])
            steering = np.exp(1j * k_wave * elements @ u)
            pulse = np.sinc(n - d / mps)
            y[k] += amp * steering[:, None] * pulse[None, :]
        noise = np.random.default_rng([a.seed, 4, k])
        y[k] += (noise.normal(size=y[k].shape) + 1j * noise.normal(size=y[k].shape)) / math.sqrt(2.0)
    meta = {
        "format": "echomap.cir.v1",
        "carrier_hz": FREQUENCY,
        "bandwidth_hz": BANDWIDTH,
        "sample_rate_hz": BANDWIDTH,
        "pulse": "sinc",
        "delay_origin_m": 0.0,
        "samples": samples,
        "elements_m": elements.tolist(),
        "processing_gain": 1.0,
        "noise_variance": 1.0,
        "snapshot_rate_hz": RATE_HZ,
        "speed": True,
        "source": f"sionna-rt scene {a.scene} seed {a.seed} (tests/sionna/walk.py --cir)",
        "snapshots": [{"t": r["t"], "gyro": r["gyro"], "speed": r["speed"]} for r in records],
    }
    with open(os.path.join(a.out, "cir.json"), "w") as f:
        json.dump(meta, f)
    np.save(os.path.join(a.out, "cir.npy"), y.astype(np.complex64))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", required=True, help="a built-in Sionna RT scene, e.g. munich, etoile, florence, san_francisco")
    ap.add_argument("--seed", type=int, default=1, help="seed of the start point, direction and noise")
    ap.add_argument(
        "--layout",
        type=int,
        help="seed of the loop and the transmitter (default: --seed); walks of one scene with the same"
        " layout share their streets and transmitter (a crowd)",
    )
    ap.add_argument("--out", required=True)
    ap.add_argument("--cir", action="store_true", help="also write the sampled channel (cir.json + cir.npy)")
    ap.add_argument("--cell", type=float, default=1.0, help="grid cell (m) of the street map")
    ap.add_argument(
        "--loop-m",
        type=float,
        nargs=2,
        default=[300.0, 500.0],
        metavar=("MIN", "MAX"),
        help="length range of the loop (m); small scenes such as simple_street_canyon need a lower MIN",
    )
    ap.add_argument("--batch", type=int, default=100, help="receivers traced at once")
    ap.add_argument("--max-depth", type=int, default=3)
    ap.add_argument(
        "--threads",
        type=int,
        default=1,
        help="Dr.Jit worker threads (default 1: the same seed gives the same walk; 0: all cores)",
    )
    a = ap.parse_args()

    import drjit as dr
    import sionna.rt as rt

    if a.threads:
        # Dr.Jit's parallel ray tracing is not bit-reproducible; one thread is
        dr.set_thread_count(a.threads)

    layout = np.random.default_rng([a.seed if a.layout is None else a.layout, 0])
    walk = np.random.default_rng([a.seed, 3])
    scene = rt.load_scene(getattr(rt.scene, a.scene))
    pts, tx, xs, ys, z = plan(scene, layout, walk, a.cell, a.loop_m)
    n = len(pts)
    dt = 1.0 / RATE_HZ
    heading = np.array([math.atan2(*(pts[min(k + 1, n - 1)] - pts[k])[::-1]) for k in range(n)])
    heading[-1] = heading[-2]
    heading = np.unwrap(heading)
    print(f"{a.scene}: loop of {n - 1} snapshots ({(n - 1) * SPEED / RATE_HZ:.0f} m), transmitter at {tx.round(1)}", file=sys.stderr)
    paths, tz = trace(scene, pts, tx, xs, ys, z, a.batch, a.max_depth, a.seed)

    # local frame: the start pose
    h0 = heading[0]
    c, s = math.cos(-h0), math.sin(-h0)

    def local(p):
        d = p - pts[0]
        return c * d[0] - s * d[1], s * d[0] + c * d[1]

    os.makedirs(a.out, exist_ok=True)
    odometry = np.random.default_rng([a.seed, 2])
    prev = []  # (track, d, world aoa, key)
    next_id = 1
    gyro_bias = 0.003
    records = []
    comps_total = 0
    for k in range(n):
        det = []
        for d, phi, pw, key, _, _ in sorted(paths[k], key=lambda p: -p[2]):
            snr_db = TX_POWER_DBM + 10.0 * math.log10(pw) - NOISE_DBM
            if snr_db < DETECT_DB:
                continue
            if any(abs(d - e[0]) < RES_D_M and abs(wrap(phi - e[1])) < RES_AOA_RAD for e in det):
                continue
            det.append((d, phi, snr_db, key))
        cur = []
        taken = set()
        for d, phi, snr_db, key in det:
            same = [p for p in prev if p[3] == key and p[0] not in taken]
            if not same:
                same = [
                    p
                    for p in prev
                    if p[0] not in taken and abs(p[1] - d) < 0.6 and abs(wrap(p[2] - phi)) < 0.08
                ]
            if same:
                track = min(same, key=lambda p: abs(p[1] - d) + abs(wrap(p[2] - phi)))[0]
            else:
                track, next_id = next_id, next_id + 1
            taken.add(track)
            cur.append((track, d, phi, key, snr_db))
        prev = [(t, d, phi, key) for t, d, phi, key, _ in cur]
        # measurement noise of each snapshot from its own stream, so that a path more or less
        # elsewhere does not shift every later draw
        noise = np.random.default_rng([a.seed, 1, k])
        comps = []
        for track, d, phi, _, snr_db in cur:
            snr = 10.0 ** (snr_db / 10.0)
            sd = math.sqrt(0.1**2 + (1.65 / math.sqrt(2.0 * snr)) ** 2)
            sa = math.sqrt(0.035**2 + (0.35 / math.sqrt(2.0 * snr)) ** 2)
            comps.append(
                {
                    "track": track,
                    "d": d + noise.normal(0.0, sd),
                    "aoa": wrap(phi - heading[k] + noise.normal(0.0, sa)),
                    "snr_db": round(snr_db, 2),
                }
            )
        comps_total += len(comps)
        rate = 0.0 if k == 0 else (heading[k] - heading[k - 1]) / dt
        gyro = 0.0 if k == 0 else rate + gyro_bias + odometry.normal(0.0, 0.005 * math.sqrt(RATE_HZ))
        speed = 1.02 * SPEED + odometry.normal(0.0, 0.05)
        records.append({"t": round(k * dt, 6), "gyro": gyro, "speed": speed, "components": comps})

    seen = sum(1 for r in records if r["components"]) / n
    if seen < 0.2:
        sys.exit(f"the transmitter is heard in {seen:.0%} of the snapshots only: try another --layout")
    header = {
        "format": "echomap.log.v1",
        "snapshot_rate_hz": RATE_HZ,
        "aoa": True,
        "speed": True,
        "source": f"sionna-rt scene {a.scene} layout {a.seed if a.layout is None else a.layout} seed {a.seed} (tests/sionna/walk.py)",
    }
    with open(os.path.join(a.out, "log.jsonl"), "w") as f:
        f.write(json.dumps(header) + "\n")
        for r in records:
            f.write(json.dumps(r) + "\n")
    poses = []
    for k in range(n):
        x, y = local(pts[k])
        poses.append({"t": round(k * dt, 6), "x": x, "y": y, "heading_rad": wrap(heading[k] - h0), "speed_mps": SPEED})
    tx_local = local(tx)
    truth = {
        "format": "echomap.truth.v1",
        "world_from_local": {"angle_rad": float(h0), "translation": [float(pts[0][0]), float(pts[0][1])]},
        "poses": poses,
        "transmitters": [{"track": 0, "state": [tx_local[0], tx_local[1], 0.0], "kind": "physical", "path": "Tx"}],
    }
    with open(os.path.join(a.out, "truth.json"), "w") as f:
        json.dump(truth, f)
    if a.cir:
        write_cir(a, paths, heading, records)
    print(
        f"wrote {a.out}: {n} snapshots, {comps_total / n:.1f} paths per snapshot, {next_id - 1} track ids; transmitter at {tz:.1f} m",
        file=sys.stderr,
    )


if __name__ == "__main__":
    main()
