"""Lost in space that never gives a wrong id: the sets in which starenv's LostInSpaceIdentifier labels any detection
with the wrong star, over many held-out centroid sets, with a 95 % upper bound on the rate of such sets.

Goal: no wrong id in 10 000 sets a field at 1 px of centroid noise per axis, 12 and 20 deg fields.

Sets are those of ``benchmarks/identify_peers.py`` (random attitudes, Hipparcos-2 to Hp 6.5 at 12 deg and 5.5 at
20 deg, stars within ``--blend-px`` of a brighter one dropped, Gaussian noise per coordinate, brightest first), drawn
from each seed of ``--seeds`` for each field.  Per (field, seed): sets solved (>= 3 correct ids, none wrong), the
per-star ID rate, and every set with a wrong id (its index, wrong and correct ids, detections), to be looked at one by
one; then, per field, the totals and the one-sided 95 % Clopper-Pearson bound on the rate of sets with a wrong id.

    python benchmarks/lis_false_ids.py [--sets N] [--seeds S ...] [--fov F ...] [--noise PX] [--blend-px PX]

Defaults: 10 000 sets, seeds 4700, 4800 and 4900 (no test draws from them), both fields, 1 px, 3 px.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from identify_peers import BLEND_PX, EPOCH, MAG_LIMIT, make_camera, make_sets, split  # run from benchmarks/
from scipy.stats import beta

from starenv.agents.base import StarMeasurements
from starenv.agents.identify.lost_in_space import LostInSpaceIdentifier
from starenv.sim.sky import load_catalog

SEEDS = (4700, 4800, 4900)


def scan(fov: int, seed: int, count: int, noise_px: float, blend_px: float, identifier) -> dict:
    """Lost in space on ``count`` sets of field ``fov`` drawn from ``seed``: solved sets, ID rate, wrong-id sets."""
    camera = make_camera(fov)
    sets = make_sets(camera, MAG_LIMIT[fov], count, np.random.default_rng(seed), noise_px, blend_px)
    solved = correct = total = 0
    wrong_sets = []
    for k, (xy, flux, hip) in enumerate(zip(split(sets, "xy"), split(sets, "flux"), split(sets, "hip"), strict=True)):
        ids = identifier.identify([StarMeasurements(xy, flux)], [camera])[0].catalog_id
        right, wrong = int(np.sum(ids == hip)), int(np.sum((ids >= 0) & (ids != hip)))
        solved, correct, total = solved + (right >= 3 and wrong == 0), correct + right, total + len(ids)
        if wrong:
            wrong_sets.append((k, wrong, right, len(ids)))
    return {"solved": solved, "id_rate": correct / max(total, 1), "wrong_sets": wrong_sets}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", type=int, default=10_000)
    parser.add_argument("--seeds", type=int, nargs="+", default=list(SEEDS))
    parser.add_argument("--fov", type=int, nargs="+", choices=sorted(MAG_LIMIT), default=sorted(MAG_LIMIT))
    parser.add_argument("--noise", type=float, default=1.0, help="centroid noise per axis (px)")
    parser.add_argument("--blend-px", type=float, default=BLEND_PX,
                        help="drop a star within this of a brighter one (0: keep every star)")
    args = parser.parse_args()
    print(f"{args.sets} sets a seed, {args.noise} px noise, stars within {args.blend_px} px of a brighter one dropped")
    for fov in args.fov:
        identifier = LostInSpaceIdentifier()
        identifier.reset([make_camera(fov)], load_catalog(MAG_LIMIT[fov], EPOCH))
        runs = []
        for seed in args.seeds:
            start = time.perf_counter()
            run = scan(fov, seed, args.sets, args.noise, args.blend_px, identifier)
            runs.append(run)
            print(f"{fov} deg, seed {seed}: {run['solved']}/{args.sets} sets solved, per-star ID {run['id_rate']:.4%}, "
                  f"sets with a wrong id {len(run['wrong_sets'])}"
                  f"{' (set, wrong, right, detections) ' + str(run['wrong_sets']) if run['wrong_sets'] else ''} "
                  f"({time.perf_counter() - start:.0f} s)")
        sets, bad = args.sets * len(runs), sum(len(run["wrong_sets"]) for run in runs)
        bound = float(beta.ppf(0.95, bad + 1, sets - bad)) if bad < sets else 1.0
        rates = [run["id_rate"] for run in runs]
        print(f"{fov} deg, all seeds: {bad} sets with a wrong id in {sets} (95 % upper bound on the rate "
              f"{bound:.1e}); per-star ID {np.median(rates):.4%} [{min(rates):.4%}-{max(rates):.4%}] over the seeds")


if __name__ == "__main__":
    main()
