"""Paper 002's comparison (Figs. 7-10, Tables 2-3) on the bundled ``paper_002`` sensor (1024 x 1024 px, 12 x 12 deg,
92 ms) as the env delivers its frames: identification rate against two-axis and three-axis rate, star position noise
and magnitude noise, for the triangle, grid and lost-in-space identifiers on the detector's centroids and for lost in
space after the trail fit (``TrailFitDeblurrer``, which reads the frame's gyro samples) before detection; with
``--weights`` also for paper 002's network (``NetworkIdentifier``: the raw frame and the same detections).

    python benchmarks/paper002_comparison.py --seed 29 --frames 200 --jobs 2 --out paper002_comparison.json
    python benchmarks/paper002_comparison.py --seed 29 --frames 200 --jobs 2 --identifiers network \
        --weights paper002_sky_small --out paper002_comparison_network.json   # the network on the same frames
    python benchmarks/paper002_comparison.py --tables paper002_comparison.json paper002_comparison_network.json
    python benchmarks/paper002_comparison.py --tables paper002_comparison.json

Frames.  Frame ``i`` of a condition is frame 0 of the scenario as the env delivers it (``StarSensor``, the scenario's
detector noise and gyro), rendered through the dataset generator (:func:`starenv.datasets.samples.render`) with a
constant rate and head 0's attitude at mid-exposure drawn uniformly over rotations from ``(--seed, i)`` -- the
boresight uniform over the sky, not centred on a star; the same ``i`` has the same attitude in every condition, so
the conditions are paired.  Rates are in the camera frame (+Z boresight): two-axis ``(w cos a, w sin a, 0)`` with
``a`` uniform; three-axis the paper's equal components ``w / sqrt(3)`` with random signs.  Position noise shifts every
star's direction (its whole trail, as the paper adds it to the trail positions of its Eq. 5) by a Gaussian of sigma
px per axis; magnitude noise adds a Gaussian (mag) to every star's Hp.  No false or missing stars.

Per frame: one detection (``CentroidDetector``, the scenario's PSF, every star found), each identifier on it; the
trail fit, then the same detector and lost in space on its output.

Scores per frame (:func:`score`).  A label is right when its detection lies within ``LABEL_RADIUS_PX`` of that
star's true trail (start -> mid -> end).  The **main star** is the navigation star (Hp <= ``NAV_MAG``, the paper's
6 Mv) nearest the true boresight.  ``main``: the attitude solved from the identifier's labels (>= 2) puts that star
nearest its boresight; ``wrong_main``: labels given but another star there; ``wrong_label``: any label wrong;
``solved``: >= 3 right labels and none wrong.  The tables (:func:`identified`) count a frame **identified** when
labels are given and none is wrong (the main star and the frame's stars named), and **wrong** when any label is
wrong, split into wrong attitudes (another main star as well) and single wrong labels.  ``main`` alone is not the
measure: the detector's centroid of a partly detected trail lies anywhere along it, so an attitude solved from right
labels of smeared stars can miss by a good part of a trail and, near the edge of the main star's cell, name its
neighbour.  Intervals: exact binomial 95 % (:func:`starenv.datasheet.binomial_interval`).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from starenv.agents.base import StepInput  # noqa: E402
from starenv.agents.blocks import wahba_svd  # noqa: E402
from starenv.agents.detect.centroid import CentroidDetector  # noqa: E402
from starenv.agents.identify.geometry import body_vectors  # noqa: E402
from starenv.agents.identify.grid import GridIdentifier  # noqa: E402
from starenv.agents.identify.lost_in_space import LostInSpaceIdentifier  # noqa: E402
from starenv.agents.identify.triangle import TriangleIdentifier  # noqa: E402
from starenv.agents.restore.trail_fit import TrailFitDeblurrer  # noqa: E402
from starenv.datasets import load_spec  # noqa: E402
from starenv.datasets.samples import draw, render  # noqa: E402
from starenv.datasheet import binomial_interval  # noqa: E402
from starenv.parallel import local_executor  # noqa: E402
from starenv.sim.sky import load_catalog  # noqa: E402

SCENARIO = "paper_002"
# Every detection goes to the identifiers, as in the bundled pipelines: a cap on the brightest takes neighbours out of
# the grid's pattern that its catalogue pattern holds (the triangle and Tetra searches take their own brightest).
MAX_STARS = None
NAV_MAG = 6.0  # navigation stars: Hp <= this (the paper's 6 Mv instrument threshold)
LABEL_RADIUS_PX = 3.0  # a label is right when its detection lies this close to the star's true trail
IDENTIFIERS = ("triangle", "grid", "lost_in_space", "lost_in_space_trail_fit")  # and "network" (with --weights)
OUTCOMES = ("main", "wrong_main", "wrong_label", "solved")
CHUNK = 25  # frames per task handed to a worker

# Conditions in the order they are run (most wanted first): (mode, rate deg/s, position sigma px, magnitude sigma)
CONDITIONS = (
    [("two", w, 0.0, 0.0) for w in (0, 4, 8, 12)] + [("three", w, 0.0, 0.0) for w in (10, 12)]
    + [("two", 0, 5.0, 0.0), ("two", 0, 0.0, 2.0), ("two", 5, 3.0, 0.0), ("two", 5, 0.0, 1.0)]
    + [("two", w, 0.0, 0.0) for w in (2, 6, 10)] + [("three", w, 0.0, 0.0) for w in (4, 6)]
    + [("two", 0, 1.0, 0.0), ("two", 0, 3.0, 0.0), ("two", 0, 0.0, 0.2), ("two", 0, 0.0, 1.0)]
)


def condition_spec(seed: int, position_sigma_px: float = 0.0, magnitude_sigma: float = 0.0):
    """The frame generator of one noise condition: ``paper_002`` frame 0, attitude uniform over rotations."""
    return load_spec({
        "name": "paper002_comparison", "kind": "centroids", "scenario": SCENARIO, "samples": 1, "seed": seed,
        "pointing": {"mode": "uniform"}, "rates": {"two_axis_dps": [0.0], "directions": 0, "roll_dps": [0.0]},
        "stars": {"variants": ["clean"], "position_sigma_px": position_sigma_px, "magnitude_sigma": magnitude_sigma}})


def condition_rate(mode: str, rate_dps: float, seed: int, index: int) -> np.ndarray:
    """Camera-frame rate (deg/s, (3,)) of frame ``index``: two-axis in a uniform direction, or three equal
    components of random signs; the draw depends on (seed, index, mode) only, not on the magnitude."""
    rng = np.random.default_rng([seed, index, 3 if mode == "three" else 2])
    if mode == "two":
        a = rng.uniform(0.0, 2.0 * np.pi)
        return np.array([rate_dps * math.cos(a), rate_dps * math.sin(a), 0.0])
    if mode == "three":
        return rate_dps / math.sqrt(3.0) * rng.choice([-1.0, 1.0], 3)
    raise ValueError(f"mode: 'two' or 'three', got {mode!r}")


def condition_frame(spec, mode: str, rate_dps: float, index: int):
    """Frame ``index`` of a condition: drawn parameters (rate replaced), the rendered :class:`Frame` and the
    :class:`StepInput` the pipeline sees (head 0's image, the frame's gyro samples, the calibrated camera)."""
    params = draw(spec, index)
    params["rate_cam_dps"] = condition_rate(mode, rate_dps, spec.seed, index)
    sensor, frame = render(spec, params)
    sc = sensor.scenario
    step = StepInput(images=[frame.heads[0].image], frame_valid=np.array([True]), time_s=frame.t_mid,
                     exposure_s=sc.exposure_s, gyro=frame.gyro, cameras=[sc.heads[0].calibrated])
    return params, frame, step


def trail_distance(xy: np.ndarray, truth, rows: np.ndarray) -> np.ndarray:
    """Distance (px) of each point ``xy`` (n, 2) to its star's true trail (start -> mid -> end; truth ``rows``)."""

    def segment(a, b):
        d = b - a
        t = np.clip(np.einsum("ij,ij->i", xy - a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12), 0.0, 1.0)
        return np.linalg.norm(xy - (a + t[:, None] * d), axis=1)

    start, mid, end = truth.xy_start[rows], truth.xy_mid[rows], truth.xy_end[rows]
    return np.minimum(segment(start, mid), segment(mid, end))


def score(stars, camera, catalog, nav_unit, nav_hip, attitude: Rotation, truth) -> dict[str, bool]:
    """The outcomes (``OUTCOMES``) of one identifier's labelled stars; see the module docstring."""
    ids = stars.catalog_id
    known = np.flatnonzero(ids >= 0)
    where = {int(h): k for k, h in enumerate(truth.catalog_id)}
    rows = np.array([where.get(int(h), -1) for h in ids[known]], dtype=np.int64)
    right = np.zeros(len(known), dtype=bool)
    seen = rows >= 0
    right[seen] = trail_distance(stars.xy[known[seen]], truth, rows[seen]) <= LABEL_RADIUS_PX
    true_boresight = camera.inertial_to_camera(attitude).inv().apply([0.0, 0.0, 1.0])
    main_hip = nav_hip[np.argmax(nav_unit @ true_boresight)]
    named = False
    if len(known) >= 2:
        body, _ = body_vectors([stars], [camera])
        cat_rows = np.searchsorted(catalog.hip, ids[known])
        estimate = Rotation.from_matrix(wahba_svd(body[known], catalog.unit[cat_rows]))
        boresight = camera.inertial_to_camera(estimate).inv().apply([0.0, 0.0, 1.0])
        named = bool(nav_hip[np.argmax(nav_unit @ boresight)] == main_hip)
    return {"main": named, "wrong_main": len(known) >= 2 and not named, "wrong_label": bool((~right).any()),
            "solved": int(right.sum()) >= 3 and bool(right.all())}


_WORKER: dict = {}


def _pipeline(weights: str | None = None):
    """This process's detector, trail fit, identifiers and catalogues (built once per worker); the network's with
    ``weights``."""
    if not _WORKER or _WORKER["weights"] != weights:
        sc = condition_spec(0).load_scenario()
        camera = sc.heads[0].calibrated
        catalog = load_catalog(sc.mag_limit, sc.epoch)
        nav = catalog.magnitude <= NAV_MAG
        agents = {"triangle": TriangleIdentifier(), "grid": GridIdentifier(), "lost_in_space": LostInSpaceIdentifier()}
        if weights is not None:
            from starenv.agents.identify.network import NetworkIdentifier  # torch: only when asked for
            agents["network"] = NetworkIdentifier(weights)
        for agent in agents.values():
            agent.reset([camera], catalog)
        _WORKER.update(weights=weights, camera=camera, catalog=catalog, nav_unit=catalog.unit[nav],
                       nav_hip=catalog.hip[nav], agents=agents, trail_fit=TrailFitDeblurrer(),
                       detector=CentroidDetector(psf_sigma_px=sc.heads[0].psf_sigma_px, max_stars=MAX_STARS))
    return _WORKER


def run_chunk(condition: tuple, seed: int, start: int, count: int, names: tuple[str, ...] = IDENTIFIERS,
              weights: str | None = None) -> dict:
    """Frames ``start .. start + count - 1`` of one condition: per identifier of ``names`` and outcome, one flag per
    frame."""
    mode, rate, sigma_px, sigma_mag = condition
    w = _pipeline(weights)
    spec = condition_spec(seed, sigma_px, sigma_mag)
    cam, det = w["camera"], w["detector"]
    flags = {n: {o: [] for o in OUTCOMES} for n in names}
    fit = "lost_in_space_trail_fit" in names
    seconds = {n: 0.0 for n in ("render", "detect", *(("trail_fit",) if fit else ()), *names)}
    for index in range(start, start + count):
        t = time.perf_counter()
        params, frame, step = condition_frame(spec, mode, float(rate), index)
        t1 = time.perf_counter()
        found = det.detect(step.images[0], cam)
        t2 = time.perf_counter()
        restored = det.detect(w["trail_fit"].deblur(step.images[0], 0, step), cam) if fit else None
        seconds["render"] += t1 - t
        seconds["detect"] += t2 - t1
        if fit:
            seconds["trail_fit"] += time.perf_counter() - t2
        for name in names:
            agent = w["agents"]["lost_in_space" if name == "lost_in_space_trail_fit" else name]
            t = time.perf_counter()
            if name == "network":
                out = agent.identify([found], [cam], None, images=step.images)[0]
            else:
                out = agent.identify([restored if name == "lost_in_space_trail_fit" else found], [cam], None)[0]
            seconds[name] += time.perf_counter() - t
            result = score(out, cam, w["catalog"], w["nav_unit"], w["nav_hip"], params["attitude"],
                           frame.heads[0].truth)
            for o in OUTCOMES:
                flags[name][o].append(result[o])
    return {"flags": flags, "seconds": seconds}


def run(frames: int, seed: int, jobs: int, conditions=CONDITIONS, out: str | None = None, log=print,
        names: tuple[str, ...] = IDENTIFIERS, weights: str | None = None) -> dict:
    """Every condition on ``frames`` frames for the identifiers ``names`` (tasks of ``CHUNK`` frames, ``jobs``
    processes); the finished conditions are written to ``out`` as each one completes, so a run cut short keeps
    them."""
    if "network" in names and weights is None:
        raise ValueError("the network needs --weights")
    tasks = [(tuple(c), seed, s, min(CHUNK, frames - s), tuple(names), weights) for c in conditions
             for s in range(0, frames, CHUNK)]
    parts: dict[tuple, dict] = {}
    done: dict[tuple, dict] = {}
    res = {"seed": seed, "frames_per_condition": frames, "weights": weights, "results": []}
    for (cond, start), part in local_executor(run_chunk, lambda a: (a[0], a[2]), jobs)(tasks):
        parts.setdefault(cond, {})[start] = part
        if sum(len(p["flags"][names[0]]["main"]) for p in parts[cond].values()) == frames:
            done[cond] = summary(cond, parts[cond])
            log(json.dumps({k: v for k, v in done[cond].items() if k != "flags"}))
            res["results"] = [done[c] for c in map(tuple, conditions) if c in done]
            if out:
                Path(out).write_text(json.dumps(res) + "\n", encoding="utf-8")
    return res


def summary(condition: tuple, chunks: dict) -> dict:
    """One condition's counts (frames in index order), per-frame flags and seconds per frame."""
    mode, rate, sigma_px, sigma_mag = condition
    ordered = [chunks[s] for s in sorted(chunks)]
    flags = {n: {o: [b for c in ordered for b in c["flags"][n][o]] for o in OUTCOMES} for n in ordered[0]["flags"]}
    frames = len(next(iter(flags.values()))["main"])
    seconds = {k: sum(c["seconds"][k] for c in ordered) / frames for k in ordered[0]["seconds"]}
    return {"mode": mode, "rate_dps": rate, "sigma_px": sigma_px, "magnitude_sigma": sigma_mag, "frames": frames,
            "counts": {n: {o: int(sum(v)) for o, v in f.items()} for n, f in flags.items()},
            "flags": {n: {o: "".join("1" if b else "0" for b in v) for o, v in f.items()} for n, f in flags.items()},
            "seconds_per_frame": seconds}


# Paper 002's own numbers (% identified; 2000 frames a level): Figs. 7-8 endpoints from the text, Fig. 9-10
# endpoints and Tables 2-3 at 5 deg/s.  Keys: (mode, rate, position sigma px, magnitude sigma) -> (network, triangle,
# grid); None where the paper gives no number.
PAPER = {
    ("two", 0, 0.0, 0.0): (97.5, 99.3, 98.2), ("two", 10, 0.0, 0.0): (29.5, 12.15, 1.95),
    ("three", 10, 0.0, 0.0): (60.4, None, None), ("three", 12, 0.0, 0.0): (30.1, 12.1, 2.2),
    ("two", 0, 5.0, 0.0): (89.0, 30.6, 69.9), ("two", 0, 0.0, 2.0): (85.1, 98.0, 70.3),
    ("two", 0, 0.0, 0.2): (None, 98.0, 98.1),
    ("two", 5, 3.0, 0.0): (79.7, 32.6, 11.0), ("two", 5, 0.0, 1.0): (57.5, 51.0, 7.05),
}
PAPER_NOTE = {("two", 0, 5.0, 0.0): "network: 'above 89 %'", ("two", 0, 0.0, 2.0): "triangle: 'about 98 %'",
              ("two", 0, 0.0, 0.2): "triangle: 'about 98 %'"}


def identified(flags: dict[str, str]) -> dict[str, int]:
    """Frames of one identifier's per-frame flags (``OUTCOMES`` as '0'/'1' strings): ``identified`` (labels given,
    none wrong), ``wrong`` (any label wrong), of them ``wrong_attitude`` (another main star named too)."""
    f = {o: np.array([c == "1" for c in v], dtype=bool) for o, v in flags.items()}
    labelled = f["main"] | f["wrong_main"]
    return {"identified": int((labelled & ~f["wrong_label"]).sum()), "wrong": int(f["wrong_label"].sum()),
            "wrong_attitude": int((f["wrong_label"] & f["wrong_main"]).sum())}


def tables(files: list[str]) -> str:
    """Markdown tables of result files (conditions merged): % identified (main star) with its 95 % interval and the
    wrong-identification rates per identifier, the paper's numbers beside."""
    rows = {}
    for f in files:  # files of the same frames (seed, frame count) with other identifiers add their columns
        res = json.loads(Path(f).read_text(encoding="utf-8"))
        for r in res["results"]:
            key = (r["mode"], r["rate_dps"], r["sigma_px"], r["magnitude_sigma"])
            if key in rows and rows[key]["frames"] == r["frames"] and rows[key].get("seed") == res["seed"]:
                rows[key]["flags"].update(r["flags"])
                rows[key]["seconds_per_frame"].update(r["seconds_per_frame"])
            else:
                rows[key] = {**r, "seed": res["seed"]}

    def pct(k: int, n: int) -> str:
        lo, hi = binomial_interval(k, n)
        return f"{100 * k / n:.1f} ({100 * lo:.1f}-{100 * hi:.1f})"

    def paper(key) -> str:
        vals = PAPER.get(key)
        return "" if vals is None else " / ".join("-" if v is None else f"{v:g}" for v in vals)

    short = {"triangle": "triangle", "grid": "grid", "lost_in_space": "LIS",
             "lost_in_space_trail_fit": "LIS + trail fit", "network": "network"}
    out = []
    sections = (("Two-axis rate (wz = 0), no noise (paper Fig. 7)", lambda k: k[0] == "two" and k[2] == 0 == k[3]),
                ("Three-axis rate (equal components), no noise (paper Fig. 8; 0 deg/s is the two-axis row)",
                 lambda k: k[0] == "three"),
                ("Position noise (paper Fig. 9 at 0 deg/s, Table 2 at 5 deg/s)", lambda k: k[2] > 0),
                ("Magnitude noise (paper Fig. 10 at 0 deg/s, Table 3 at 5 deg/s)", lambda k: k[3] > 0))
    for title, sel in sections:
        keys = sorted(k for k in rows if sel(k))
        if not keys:
            continue
        names = [n for n in (*IDENTIFIERS, "network") if all(n in rows[k]["flags"] for k in keys)]
        head = ["w (deg/s)", "sigma (px)", "sigma (mag)", "frames"] + [f"{short[n]}: identified %" for n in names]
        head += ["wrong: any label / attitude (frames): " + ", ".join(short[n] for n in names),
                 "paper: network / triangle / grid %"]
        out += [f"**{title}** (identified: % of frames, exact 95 % interval)", "",
                "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for k in keys:
            r = rows[k]
            n = r["frames"]
            c = {name: identified(r["flags"][name]) for name in names}
            cells = [f"{k[1]:g}", f"{k[2]:g}", f"{k[3]:g}", str(n)]
            cells += [pct(c[name]["identified"], n) for name in names]
            cells.append(", ".join(f"{c[name]['wrong']} / {c[name]['wrong_attitude']}" for name in names))
            cells.append(paper(k) + (f" ({PAPER_NOTE[k]})" if k in PAPER_NOTE else ""))
            out.append("| " + " | ".join(cells) + " |")
        out.append("")
    seconds: dict[str, list[float]] = {}
    for r in rows.values():
        for name, s in r["seconds_per_frame"].items():
            seconds.setdefault(name, []).append(s)
    out += ["| step | mean ms per frame (median over conditions) |", "|---|---|"]
    out += [f"| {name} | {1e3 * float(np.median(v)):.0f} |" for name, v in seconds.items()]
    return "\n".join(out)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=200, help="frames per condition")
    p.add_argument("--seed", type=int, default=29, help="seed of the frame draws (attitudes, rate directions, noise)")
    p.add_argument("--jobs", type=int, default=1, help="worker processes")
    p.add_argument("--conditions", type=int, default=len(CONDITIONS),
                   help=f"run the first N of the {len(CONDITIONS)} conditions (in the order of CONDITIONS)")
    p.add_argument("--out", default=None, help="write the results as JSON here")
    p.add_argument("--weights", default=None, help="paper 002's network's weights (a run folder or a shipped name)")
    p.add_argument("--identifiers", default=",".join(IDENTIFIERS),
                   help=f"comma-separated, of {', '.join(IDENTIFIERS)}, network (needs --weights); a run of other "
                   "identifiers on the same seed and frames adds columns to the tables")
    p.add_argument("--tables", nargs="+", default=None, metavar="FILE.json",
                   help="print the markdown tables of earlier --out files (merged) and exit")
    args = p.parse_args()
    if args.tables:
        print(tables(args.tables))
        return 0
    t0 = time.perf_counter()
    names = tuple(args.identifiers.split(","))
    unknown = sorted(set(names) - {*IDENTIFIERS, "network"})
    if unknown:
        p.error(f"--identifiers: unknown {', '.join(unknown)}")
    res = run(args.frames, args.seed, args.jobs, CONDITIONS[:args.conditions], args.out, names=names,
              weights=args.weights)
    res["wall_s"] = round(time.perf_counter() - t0, 1)
    print("wall", res["wall_s"], "s")
    if args.out:
        Path(args.out).write_text(json.dumps(res) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
