"""Wrong ids of lost in space and tracking on paper 004's three 6 deg heads, held out: frames from seeds given on the
command line, each identified from scratch (lost in space) and from a compass prior (tracking, a prior off by
``--prior-deg`` per axis, 1 sigma: beyond the tracking gate, as paper 004's reference [7] points its heads).

A pattern in one small head leaves the roll about it loose, so another head's stars move by several match radii;
this is where a chance match can take an id.  Prints, per seed and noise level, the frames with a wrong id (and the
wrong ids) out of ``--frames``, apart from the ids of a star within ``MERGE_PX`` of the true one (listed as merged:
the frames hold both stars of such a pair as two detections, where a sensor sees one spot, and the identifiers
label it with the brighter star), the one-sided 95 % Clopper-Pearson bound on the rate of such frames over all seeds,
and the per-star ID rate with its spread over the seeds::

    python benchmarks/multi_head_false_ids.py [--seeds 5100 5200 5300] [--frames 1000] [--noise 0.5 1.0]
                                              [--prior-deg 2.0]

Frames are :func:`starenv.datasets.star_fields.centroid_set` of the navigation stars (Hp <= 6.5) at attitudes uniform
on SO(3) with Gaussian centroid noise; both identifiers keep their defaults (``centroid_noise_px`` 0.5) and are reset
with the catalogue to Hp 7.5, as in ``benchmarks/paper004_identification.py``.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import beta

from starenv import scenario as scenario_mod
from starenv.agents.base import StarMeasurements
from starenv.agents.identify.geometry import MERGE_PX
from starenv.agents.identify.lost_in_space import LostInSpaceIdentifier
from starenv.agents.identify.tracking import TrackingIdentifier
from starenv.datasets.star_fields import centroid_set, random_attitude
from starenv.sim.sky import load_catalog

SEEDS = (5100, 5200, 5300)  # default seeds (no test draws from them)


def heads_and_catalogues() -> tuple[list, object, object]:
    """paper_004's calibrated cameras, the catalogue the frames hold (Hp <= 6.5) and the identifiers' (Hp <= 7.5,
    deeper, as in paper004_identification.py)."""
    sc = scenario_mod.load("paper_004")
    return [h.calibrated for h in sc.heads], load_catalog(6.5, sc.epoch), load_catalog(7.5, sc.epoch)


def draw_frames(visible, cameras: list, seed: int, count: int, noise_px: float, prior_deg: float) -> list:
    """``count`` (centroid set, compass prior) of ``visible``'s stars at attitudes uniform on SO(3) drawn from
    ``seed``, ``noise_px`` per axis, the prior off by ``prior_deg`` per axis (1 sigma)."""
    rng = np.random.default_rng(seed)
    frames = []
    for _ in range(count):
        attitude = random_attitude(rng)
        cs = centroid_set(visible, cameras, attitude, noise_px, rng)
        frames.append((cs, Rotation.from_rotvec(rng.normal(0.0, math.radians(prior_deg), 3)) * attitude))
    return frames


def count(identifier, cameras, frames: list, with_prior: bool, catalog) -> tuple[int, int, int, int, int]:
    """(frames with a wrong id, wrong ids, ids of a star merged with the true one, correct ids, stars) of
    ``identifier`` over ``frames``; ``catalog`` holds every star it can name."""
    row_of = {hip: row for row, hip in enumerate(catalog.hip.tolist())}
    cos_merge = math.cos(MERGE_PX / max(cam.fx for cam in cameras))
    bad = wrong = merged = correct = present = 0
    for cs, prior in frames:
        stars = [StarMeasurements(x, f) for x, f in zip(cs.xy, cs.flux, strict=True)]
        out = identifier.identify(stars, cameras, prior if with_prior else None)
        claimed, true = np.concatenate([o.catalog_id for o in out]), np.concatenate(cs.hip)
        other = (claimed >= 0) & (claimed != true)
        close = sum(catalog.unit[row_of[c]] @ catalog.unit[row_of[t]] > cos_merge
                    for c, t in zip(claimed[other].tolist(), true[other].tolist(), strict=True))
        w = int(np.count_nonzero(other)) - close
        bad, wrong, merged = bad + (w > 0), wrong + w, merged + close
        correct, present = correct + int(np.count_nonzero((claimed == true) & (true >= 0))), present + len(true)
    return bad, wrong, merged, correct, present


def upper_bound(failures: int, trials: int) -> float:
    """One-sided 95 % Clopper-Pearson upper bound on a rate from ``failures`` in ``trials``."""
    return 1.0 if failures >= trials else float(beta.ppf(0.95, failures + 1, trials - failures))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=list(SEEDS))
    parser.add_argument("--frames", type=int, default=1000, help="frames a seed and noise level")
    parser.add_argument("--noise", type=float, nargs="+", default=[0.5, 1.0], help="centroid noise per axis (px)")
    parser.add_argument("--prior-deg", type=float, default=2.0, help="tracking prior's error per axis (1 sigma)")
    args = parser.parse_args()
    cameras, catalog, onboard = heads_and_catalogues()
    lis = LostInSpaceIdentifier()
    lis.reset(cameras, onboard)
    tracker = TrackingIdentifier(fallback=lis)
    tracker.reset(cameras, onboard)
    methods = {"lost in space": (lis, False), f"tracking, prior {args.prior_deg:g} deg": (tracker, True)}
    print(f"paper_004's three heads, Hp <= 6.5; {args.frames} frames a seed and noise level\n")
    print(f"{'method':24} | {'noise px':>8} | {'seed':>5} | {'frames with a wrong id':>22} | {'wrong ids':>9} | "
          f"{'merged':>6} | {'per-star ID':>11} | {'ms a frame':>10}")
    totals = {}
    for noise in args.noise:
        for seed in args.seeds:
            frames = draw_frames(catalog, cameras, seed, args.frames, noise, args.prior_deg)
            for name, (identifier, with_prior) in methods.items():
                start = time.perf_counter()
                bad, wrong, merged, correct, present = count(identifier, cameras, frames, with_prior, onboard)
                ms = 1e3 * (time.perf_counter() - start) / len(frames)
                totals.setdefault((name, noise), []).append((bad, correct / present))
                print(f"{name:24} | {noise:8.2f} | {seed:5d} | {bad:>12} / {len(frames):<7} | {wrong:9d} | "
                      f"{merged:6d} | {correct / present:11.2%} | {ms:10.2f}")
    print(f"\nover seeds {', '.join(map(str, args.seeds))}: frames with a wrong id (95 % bound on their rate), "
          f"per-star ID median [min, max]")
    for (name, noise), rows in totals.items():
        bad = sum(b for b, _ in rows)
        rates = np.array([r for _, r in rows])
        trials = args.frames * len(rows)
        print(f"{name:24} {noise:5.2f} px: {bad} in {trials} ({upper_bound(bad, trials):.1e}); "
              f"ID {np.median(rates):.2%} [{rates.min():.2%}, {rates.max():.2%}]")


if __name__ == "__main__":
    main()
