"""Sim to real: paper 002's network trained only on frames simulated for a real camera's twin, run on that camera's
real frames, beside the same fields simulated by the twin (the control).

The camera is tetra3's test camera; its twin is ``docs/real_frames/tetra3_twin.toml`` (``starenv calibrate``), the
weights ``tetra3_twin_sky`` (trained on ``datasets/tetra3_twin_sky.toml`` only; docs/paper002_identification.md).
Every frame is first solved by the project's lost-in-space solver with the twin camera (``FrameSolver``, no field
search); its attitude and labels are the reference (that solver is checked against cedar-solve on these frames:
docs/real_frames.md).  Then, for each background (``median``: the frame's median, as in training; ``local``:
a 5 x 5 block median, :func:`starenv.datasets.preprocess.network_input`) and each search (``centre_stars`` x
``top_k``):

* frame level: the network identifier inside the same solver; solved or refused, its labels against the reference
  (a wrong label is a detection labelled with another star than the reference gives it), the attitude's difference
  from the reference (arcsec), and for a refused frame its cause: whether any of its centre detections had its
  reference star among its ``top_k`` candidates;
* star level: each navigation star (a class) the reference identifies, ranked by the network with the input centred
  on it: top-1 and top-5.

The control renders each reference attitude through the twin (``docs/real_frames/tetra3_twin_scenario.toml``, noise
seed ``--seed + k``) and scores its truth the same way.

    python benchmarks/paper002_real.py [--frames DIR] [--seed 31] [--json OUT]

``--frames``: a folder of the camera's frames (default: the three committed in ``tests/data/real``; tetra3's
``test_data/`` holds all eight, as TIFF).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from starenv import scenario as scenario_mod  # noqa: E402
from starenv.agents.identify.network import NetworkIdentifier  # noqa: E402
from starenv.agents.pipeline import Pipeline  # noqa: E402
from starenv.datasheet import binomial_interval  # noqa: E402
from starenv.env import StarSensorEnv  # noqa: E402
from starenv.real import FrameSolver, read_frame  # noqa: E402
from starenv.real.solve import LOST_IN_SPACE, radec_roll  # noqa: E402

CAMERA = ROOT / "docs" / "real_frames" / "tetra3_twin.toml"
SCENARIO = ROOT / "docs" / "real_frames" / "tetra3_twin_scenario.toml"
COMMITTED = ROOT / "tests" / "data" / "real"
WEIGHTS = "tetra3_twin_sky"
EPOCH = 2019.58  # the frames' (2019-07-29)
BACKGROUNDS = ("median", "local")
SEARCHES = ((5, 3, None), (5, 3, 20), (15, 10, 20))  # (centre_stars, top_k, brightest): the default and two others
ARCSEC = 180.0 / np.pi * 3600.0


def frame_files(folder: Path | None) -> list[Path]:
    """The frames to measure: every TIFF or PNG of ``folder``, or the committed ones."""
    if folder is None:
        return sorted(COMMITTED.glob("2019-*"))
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in (".tif", ".tiff", ".png"))


def rendered(scenario: dict, attitude, seed: int):
    """The twin's frame at the ICRS -> camera ``attitude`` (noise seed ``seed``): head 0 of its first frame."""
    ra, dec, roll = radec_roll(attitude)
    motion = {"kind": "constant_rate", "rate_dps": [0.0, 0.0, 0.0], "initial_ra_deg": ra, "initial_dec_deg": dec,
              "initial_roll_deg": roll}
    env = StarSensorEnv(scenario, overrides={"motion": motion})
    env.sensor.reset(seed)
    return env.sensor.next_frame().heads[0]


def star_level(ident: NetworkIdentifier, image: np.ndarray, xy: np.ndarray, hip: np.ndarray) -> tuple[int, int, int]:
    """(top-1 hits, top-5 hits, stars) of the class stars among ``hip`` at ``xy`` (px), ranked centred on each."""
    keep = np.isin(hip, ident.classes)
    if not keep.any():
        return 0, 0, 0
    ranked, _ = ident.rank(image, xy[keep])
    truth = hip[keep][:, None]
    return int((ranked[:, :1] == truth).sum()), int((ranked[:, :5] == truth).any(axis=1).sum()), int(keep.sum())


def frame_level(solver: FrameSolver, image: np.ndarray, labels: dict, reference) -> dict:
    """The network solver's result on ``image`` against the reference ``labels`` ((x, y) rounded -> HIP)."""
    ident = solver.pipeline.agents["identifier"]
    got = solver.solve(image)
    out = {"solved": bool(got.solved), "stars": got.stars_identified}
    if got.solved:
        out["wrong"] = sum(1 for s in got.stars if labels.get((round(s.x_px, 2), round(s.y_px, 2)), s.hip) != s.hip)
        out["diff_arcsec"] = float((reference * got.attitude.inv()).magnitude() * ARCSEC)
        out["p_false"] = ident.last.get("p_false")
        return out
    # refused: was the reference star of any centre detection among that detection's candidates?
    stars = solver.pipeline.agents["detector"].detect(image, solver.camera)
    centre = stars.xy[ident.centre_detections(stars, solver.camera)]
    ranked, _ = ident.rank(image, centre)
    truth = [labels.get((round(x, 2), round(y, 2)), -1) for x, y in centre]
    out["candidate_right"] = int(sum(t in ranked[i, : ident.top_k] for i, t in enumerate(truth) if t >= 0))
    out["centre_classes"] = int(sum(t in set(ident.classes.tolist()) for t in truth))
    return out


def search_key(background: str, centre_stars: int, top_k: int, brightest: int | None) -> str:
    """The name of one identifier set-up in the rows and the summary."""
    return f"{background} {centre_stars}x{top_k} of {brightest or 'all'}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=Path, default=None, help="folder of the camera's frames (default: committed)")
    p.add_argument("--weights", default=WEIGHTS)
    p.add_argument("--seed", type=int, default=31, help="the control's noise seeds: seed + frame index")
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    files = frame_files(args.frames)
    if not files:
        raise SystemExit(f"no frames in {args.frames}")
    camera = scenario_mod.load_camera(CAMERA).camera
    scenario = tomllib.loads(SCENARIO.read_text(encoding="utf-8"))
    reference_solver = FrameSolver(camera, Pipeline(**LOST_IN_SPACE), epoch=EPOCH, fov_tolerance=0.0)
    solvers = {}
    for bg in BACKGROUNDS:
        for cs, top, bright in SEARCHES:
            options = {"weights": args.weights, "background": bg, "centre_stars": cs, "top_k": top,
                       "brightest": bright}
            pipeline = Pipeline(predictor=None, identifier="starenv.agents.identify:NetworkIdentifier",
                                options={"identifier": options})
            solvers[bg, cs, top, bright] = FrameSolver(camera, pipeline, epoch=EPOCH, fov_tolerance=0.0)
    rows, t0 = [], time.perf_counter()
    for k, path in enumerate(files):
        image = read_frame(path)
        ref = reference_solver.solve(image, file=str(path))
        row = {"file": path.name, "reference_solved": bool(ref.solved), "reference_stars": ref.stars_identified}
        if not ref.solved:
            rows.append(row)
            continue
        labels = {(round(s.x_px, 2), round(s.y_px, 2)): s.hip for s in ref.stars}
        xy = np.array([[s.x_px, s.y_px] for s in ref.stars])
        hip = np.array([s.hip for s in ref.stars])
        sim = rendered(scenario, ref.attitude, args.seed + k)
        seen = sim.truth.detectable & np.isin(sim.truth.catalog_id, hip)
        sim_xy, sim_hip = sim.truth.xy_centroid[seen], sim.truth.catalog_id[seen]
        for (bg, cs, top, bright), solver in solvers.items():
            ident = solver.pipeline.agents["identifier"]
            key = search_key(bg, cs, top, bright)
            row[f"real {key}"] = frame_level(solver, image, labels, ref.attitude)
            if (cs, top, bright) == SEARCHES[0]:
                row[f"real stars {bg}"] = star_level(ident, image, xy, hip)
                row[f"sim stars {bg}"] = star_level(ident, sim.image, sim_xy, sim_hip)
            # the control: the twin's frame at the reference attitude, whose solution is judged against that attitude
            got = solver.solve(sim.image)
            row[f"sim {key}"] = {"solved": bool(got.solved), "stars": got.stars_identified,
                                 "diff_arcsec": float((ref.attitude * got.attitude.inv()).magnitude() * ARCSEC)
                                 if got.solved else None}
        rows.append(row)
        print(json.dumps(row), flush=True)
    summary = {"frames": len(files), "seconds": round(time.perf_counter() - t0, 1)}
    print(f"\n{len(files)} frames, {summary['seconds']} s; reference solved "
          f"{sum(r['reference_solved'] for r in rows)}")
    print("\n| background | centre stars x top k, among the brightest | real: solved | wrong labels | sim: solved |")
    print("|---|---|---|---|---|")
    for bg in BACKGROUNDS:
        for cs, top, bright in SEARCHES:
            key = search_key(bg, cs, top, bright)
            real = [r[f"real {key}"] for r in rows if r["reference_solved"]]
            sim = [r[f"sim {key}"] for r in rows if r["reference_solved"]]
            solved = sum(x["solved"] for x in real)
            lo, hi = binomial_interval(solved, len(real))
            summary[f"real {key}"] = {"solved": solved, "of": len(real), "wrong": sum(x.get("wrong", 0) for x in real)}
            summary[f"sim {key}"] = {"solved": sum(x["solved"] for x in sim), "of": len(sim)}
            wrong, sim_solved = summary[f"real {key}"]["wrong"], summary[f"sim {key}"]["solved"]
            print(f"| {bg} | {cs} x {top}, {bright or 'all'} | {solved}/{len(real)} "
                  f"({100 * lo:.0f}-{100 * hi:.0f} %) | {wrong} | {sim_solved}/{len(sim)} |")
    print("\n| background | real: star top-1 | top-5 | sim (same fields): star top-1 | top-5 |")
    print("|---|---|---|---|---|")
    for bg in BACKGROUNDS:
        real = np.sum([r[f"real stars {bg}"] for r in rows if r["reference_solved"]], axis=0)
        sim = np.sum([r[f"sim stars {bg}"] for r in rows if r["reference_solved"]], axis=0)
        summary[f"stars {bg}"] = {"real": real.tolist(), "sim": sim.tolist()}
        print(f"| {bg} | {real[0]}/{real[2]} ({100 * real[0] / max(1, real[2]):.0f} %) | {real[1]}/{real[2]} | "
              f"{sim[0]}/{sim[2]} ({100 * sim[0] / max(1, sim[2]):.0f} %) | {sim[1]}/{sim[2]} |")
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "summary": summary}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
