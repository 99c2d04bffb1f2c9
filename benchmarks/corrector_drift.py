"""Paper 003's on-orbit corrector on a camera that drifts with temperature, against its forgetting factor.

``leo_distortion`` (550 km nadir orbit at 1 frame/s, barrel + tangential + thin prism, uncalibrated), its head given a
temperature schedule (``[heads.thermal]``): the focal length and a distortion drift follow the temperature, so the
camera leaves its ground calibration along the run.  The corrector starts from least-squares ground weights fitted at
the reference temperature (``--ground-frames`` frames of random sky) and learns frame by frame (``learn_frame``, the
pipeline's path: correct, solve the attitude, learn; ``--starts zero``: from zero weights instead, as
``leo_distortion``'s pipeline does), the star pairs taken from ``orbit_pairs`` (0.05 px centroid
noise, every star taken as identified).  Residual: per axis, the mean |corrected - attitude-fitted reference| over the
frame's stars at their noise-free positions (the part no solved attitude absorbs, as in
``benchmarks/paper003_distortion.py``), checked every 10 frames; reported as its median over the last fifth of the run
and its largest value from frame 500 on (a quarter of the run if shorter: after the start-up), the larger axis.

Cases: ``tune`` (the drift the default was chosen on), ``held-out`` (another orbit phase, another temperature
profile, another drift field, other noise seeds) and the two without drift (``static``: the same cameras at a
constant temperature), each with the learners' forgetting factors ``--lams``.

    python benchmarks/corrector_drift.py [--frames 2000] [--ground-frames 100] [--lams 1 0.995 0.99 0.98 0.95]
        [--cases tune held-out] [--starts ground zero] [--no-static] [--no-drift]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from starenv import scenario as scenario_mod
from starenv.agents.correct.legendre import (
    LegendreCorrector,
    LegendreModel,
    attitude_fit_residual,
    fit_least_squares,
    learn_frame,
)
from starenv.datasets.pairs import frame_pairs, orbit_pairs
from starenv.sim.sky import load_catalog

# Each case: orbit phase overrides, the thermal table (None: static at the reference), the pairs' noise seed.
CASES = {
    "tune": ({"motion.arg_latitude_deg": 10.0}, {
        "temperature_c": [20.0, 40.0], "times_s": [0.0, 2000.0], "focal_length_ppm_per_c": 50.0,
        "distortion_per_c": {"kind": "radial", "q1": 5e-5}}, 0),
    "held-out": ({"motion.arg_latitude_deg": 130.0, "motion.raan_deg": 200.0}, {
        "temperature_c": [20.0, 38.0, 27.0, 45.0], "times_s": [0.0, 600.0, 1300.0, 2000.0],
        "focal_length_ppm_per_c": -40.0, "distortion_per_c": {"kind": "composite", "models": [
            {"kind": "radial", "q1": -3e-5, "q2": 2e-5}, {"kind": "tangential", "p1": 1.5e-5, "p2": -1e-5}]}}, 7),
}


def run_case(name: str, drift: bool, frames: int, ground_frames: int, lams: list[float], start: str) -> None:
    orbit, thermal, seed = CASES[name]
    overrides = dict(orbit)
    if drift:
        overrides["heads.0.thermal"] = thermal
    sc = scenario_mod.load("leo_distortion", overrides)
    cam = sc.heads[0].calibrated
    catalog = load_catalog(sc.mag_limit, sc.epoch)
    ground = [frame_pairs(sc, seed + 1, i) for i in range(ground_frames)]  # at the reference temperature
    gm, gr = (np.concatenate([getattr(p, k) for p in ground]) for k in ("measured", "reference"))
    folder = tempfile.TemporaryDirectory()
    weights = str(Path(folder.name) / "ground.npz")
    LegendreModel(fit_least_squares(gm, gr, cam)).save(weights)
    pairs = [orbit_pairs(sc, seed, i) for i in range(frames)]
    label = f"{name}, {'drifting' if drift else 'static'}, {start} start"
    for lam in lams:
        corrector = LegendreCorrector(learner="rls", weights=weights if start == "ground" else None,
                                      learner_options={"lam": lam})
        corrector.reset([cam], catalog)
        checked, values = [], []
        t0 = time.perf_counter()
        for i, p in enumerate(pairs):
            if i % 10 == 0 or i == frames - 1:
                checked.append(i)
                values.append(attitude_fit_residual(corrector.models[0], p.distorted, p.catalog_id, cam, catalog).max())
            learn_frame(corrector, p.measured, p.catalog_id, cam, catalog)
        spent = (time.perf_counter() - t0) / frames * 1e3
        values, checked = np.array(values), np.array(checked)
        tail = np.median(values[checked >= 0.8 * frames])
        worst = values[checked >= min(500, frames // 4)].max()
        print(f"| {label} | {lam:g} | {values[0]:.4f} | {tail:.4f} | {worst:.4f} | {spent:.2f} |")
    folder.cleanup()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=2000)
    parser.add_argument("--ground-frames", type=int, default=100)
    parser.add_argument("--lams", type=float, nargs="+", default=[1.0, 0.995, 0.99, 0.98, 0.95])
    parser.add_argument("--cases", nargs="+", choices=list(CASES), default=list(CASES))
    parser.add_argument("--static", action=argparse.BooleanOptionalAction, default=True)
    parser.add_argument("--drift", action=argparse.BooleanOptionalAction, default=True)
    parser.add_argument("--starts", nargs="+", choices=["ground", "zero"], default=["ground"])
    args = parser.parse_args()
    print("| case | lam | residual at the start (px) | median over the last fifth (px) | largest from frame 500 (px) "
          "| ms per frame |")
    print("|---|---|---|---|---|---|")
    drifts = [d for d, on in ((True, args.drift), (False, args.static)) if on]
    for name in args.cases:
        for drift in drifts:
            for start in args.starts:
                run_case(name, drift, args.frames, args.ground_frames, args.lams, start)


if __name__ == "__main__":
    main()
