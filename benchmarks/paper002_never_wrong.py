"""Paper 002's network identifier off its training distribution: how often it returns a wrong attitude, refuses, or
is right, with a 95 % interval on the wrong rate.

    python benchmarks/paper002_never_wrong.py [--frames N] [--seed S ...] [--weights DIR] [--spec SPEC]
        [--out FILE.json]

Frames (each a pure function of (seed, index)): head 0's boresight uniform in the weights' sky patch (the cap of
``pointing.radius_deg`` about the patch centre of the weights' dataset spec, ``--spec``, default
``datasets/paper002_orion.toml``, so off any class star and near the patch edge partly outside it; the whole sky
for ``datasets/paper002_sky_small.toml``), roll uniform, two-axis rate uniform in 10-12 deg/s in a uniform direction
plus a roll rate of 0 or +-6 deg/s, one of clean / false-star / missing-star (1-2 stars changed),
``MAGNITUDE_SIGMA`` mag of magnitude noise on every star, paper_002's sensor noise on the spec's sensor, each frame
read out whole as the env delivers it.  One detection (CentroidDetector, the 30 brightest), then the identifier.

Per frame: **refused** when no attitude is returned; **wrong** when one is and any of its labels is wrong by the
project's scoring rule (:mod:`starenv.scoring`: the labelled star's true trail, start to end, passes further than
``CENTROID_GATE_PX`` from the detection; a wrong main star or a flipped roll labels every detection wrongly); **right**
otherwise.  Labels are judged against the real sky: a star a missing-star frame removed from the sky it renders is
still in the sky the identifier knows (one member of a close double, or a star another star's trail crosses), so its
trail is computed from the catalogue under the frame's true motion and judged by the same rule.
The attitude's error from the true mid-exposure attitude is kept for the right frames (``max_right_error_deg``): at
10-12 deg/s a trail is a degree long on the 1024 px sensor and its detections may be pieces of it, so a right
attitude can be tenths of a degree off.  The 95 % interval on the wrong rate is Clopper-Pearson.
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

from starenv.agents.detect.centroid import CentroidDetector  # noqa: E402
from starenv.datasets import load_spec  # noqa: E402
from starenv.datasets.samples import draw, render  # noqa: E402
from starenv.datasheet import binomial_interval  # noqa: E402
from starenv.scoring import CENTROID_GATE_PX, trail_distance  # noqa: E402
from starenv.sim.conventions import pointing, radec_to_unit, unit_to_radec  # noqa: E402
from starenv.sim.sky import load_catalog  # noqa: E402

SPEC = ROOT / "datasets" / "paper002_orion.toml"
MAX_STARS = 30  # detections handed to the identifier (the brightest)
RATE_DPS = (10.0, 12.0)  # two-axis resultant, uniform
ROLL_DPS = (0.0, 6.0, -6.0)
MAGNITUDE_SIGMA = 0.3  # mag, on every star


def off_spec(seed: int, spec: str | Path = SPEC):
    """The weights' dataset spec with every star variant and magnitude noise, drawing from ``seed``, its frames read
    out whole."""
    base = load_spec(spec).to_dict()
    base.update(name="paper002_never_wrong", seed=seed, samples=1, readout="frame")
    base["stars"] = {**base["stars"], "variants": ["clean", "false", "missing"], "magnitude_sigma": MAGNITUDE_SIGMA}
    return load_spec(base)


def cap_direction(rng: np.random.Generator, centre: np.ndarray, radius_rad: float) -> np.ndarray:
    """A unit vector uniform on the sphere's cap of ``radius_rad`` about the unit vector ``centre``."""
    cos_off = 1.0 - rng.uniform() * (1.0 - math.cos(radius_rad))
    sin_off = math.sqrt(max(0.0, 1.0 - cos_off**2))
    a = rng.uniform(0.0, 2.0 * math.pi)
    e1 = np.cross(centre, [0.0, 0.0, 1.0] if abs(centre[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(centre, e1)
    return cos_off * centre + sin_off * (math.cos(a) * e1 + math.sin(a) * e2)


def frame(spec, index: int):
    """Frame ``index``: drawn parameters with the pointing and rate replaced (see the module docstring), and the
    rendered :class:`Frame`."""
    params = draw(spec, index)
    rng = np.random.default_rng([spec.seed, index, 29])
    p = spec.pointing
    centre = radec_to_unit(math.radians(p.center_ra_deg), math.radians(p.center_dec_deg))
    ra, dec = unit_to_radec(cap_direction(rng, centre, math.radians(p.radius_deg)))
    mounting = spec.load_scenario().heads[0].camera.mounting
    params["main"] = -1
    params["attitude"] = mounting.inv() * pointing(float(ra), float(dec), rng.uniform(0.0, 2.0 * math.pi))
    w, a = rng.uniform(*RATE_DPS), rng.uniform(0.0, 2.0 * math.pi)
    params["rate_cam_dps"] = np.array([w * math.cos(a), w * math.sin(a), ROLL_DPS[rng.integers(len(ROLL_DPS))]])
    return params, render(spec, params)[1]


def run(frames: int, seeds: list[int], agent=None, log=print, spec: str | Path = SPEC) -> dict:
    """Tally wrong / refused / right over ``frames`` frames of each seed of ``spec``'s sensor and sky; ``agent`` a
    NetworkIdentifier (default: the shipped Orion weights, default settings)."""
    if agent is None:
        from starenv.agents.identify.network import NetworkIdentifier

        agent = NetworkIdentifier("paper002_orion")
    spec0 = off_spec(seeds[0], spec)
    sc = spec0.load_scenario()
    cam = sc.heads[0].calibrated
    catalog = load_catalog(sc.mag_limit, sc.epoch)
    agent.reset([cam], catalog)
    detector = CentroidDetector(psf_sigma_px=sc.heads[0].psf_sigma_px, max_stars=MAX_STARS)
    tally = {"wrong": 0, "refused": 0, "right": 0}
    wrong_frames, right_error_deg = [], [0.0]
    for seed in seeds:
        frames_spec = off_spec(seed, spec)
        for index in range(frames):
            params, fr = frame(frames_spec, index)
            head = fr.heads[0]
            out = agent.identify([detector.detect(head.image, cam)], [cam], None, [head.image])
            if not agent.last.get("verified"):
                tally["refused"] += 1
                continue
            error_deg = math.degrees((agent.last["attitude"] * params["attitude"].inv()).magnitude())
            wrong_labels = wrongly_labelled(out[0], head.truth, catalog, sc.heads[0].camera, params, sc.exposure_s)
            if wrong_labels:
                tally["wrong"] += 1
                wrong_frames.append({"seed": seed, "index": index, "error_deg": round(error_deg, 3),
                                     "wrong_labels": wrong_labels, "p_false": agent.last.get("p_false"),
                                     "matched": agent.last.get("matched")})
                log(json.dumps(wrong_frames[-1]))
                continue
            tally["right"] += 1
            right_error_deg.append(error_deg)
    n = frames * len(seeds)
    low, high = binomial_interval(tally["wrong"], n)
    return {"frames": n, "seeds": seeds, **tally, "wrong_rate_95": [low, high], "right_rate": tally["right"] / n,
            "wrong_frames": wrong_frames, "max_right_error_deg": max(right_error_deg), "max_false": agent.max_false}


def wrongly_labelled(stars, truth, catalog, camera, params: dict, exposure_s: float) -> int:
    """Labels of ``stars`` that are wrong by :mod:`starenv.scoring`'s rule, judged against the real sky (see the
    module docstring): a labelled star the frame did not render gets its trail from ``catalog`` under the constant
    rate and mid-exposure attitude of ``params``, through the true ``camera``."""
    labelled = np.flatnonzero(stars.catalog_id >= 0)
    rows = {int(h): k for k, h in enumerate(truth.catalog_id)}
    start, end = np.empty((len(labelled), 2)), np.empty((len(labelled), 2))
    rate_body = camera.mounting.inv().apply(np.radians(params["rate_cam_dps"]))
    for n, i in enumerate(labelled):
        k = rows.get(int(stars.catalog_id[i]), -1)
        if k >= 0:
            start[n], end[n] = truth.xy_start[k], truth.xy_end[k]
            continue
        unit = catalog.unit[np.searchsorted(catalog.hip, stars.catalog_id[i])].copy()
        for out, dt in ((start, -0.5 * exposure_s), (end, 0.5 * exposure_s)):
            attitude = Rotation.from_rotvec(-rate_body * dt) * params["attitude"]  # ConstantRate about mid-exposure
            out[n] = camera.project(camera.inertial_to_camera(attitude).apply(unit[None]))[0][0]
    return int((trail_distance(stars.xy[labelled], start, end) > CENTROID_GATE_PX).sum())


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=1000, help="frames per seed")
    p.add_argument("--seed", type=int, nargs="+", default=[29], help="one or more seeds of the frames")
    p.add_argument("--weights", default="paper002_orion", help="network run folder or shipped name (default: the "
                   "shipped Orion weights, those of the default --spec)")
    p.add_argument("--spec", default=str(SPEC), help="the weights' dataset spec: their sensor and sky patch")
    p.add_argument("--max-false", type=float, default=None, help="the identifier's max_false (default: its own)")
    p.add_argument("--out", default=None, help="write the results as JSON here")
    args = p.parse_args()
    from starenv.agents.identify.network import NetworkIdentifier

    kwargs = {} if args.max_false is None else {"max_false": args.max_false}
    agent = NetworkIdentifier(args.weights, **kwargs)
    t0 = time.perf_counter()
    res = run(args.frames, args.seed, agent, spec=args.spec)
    res["wall_s"] = round(time.perf_counter() - t0, 1)
    low, high = res["wrong_rate_95"]
    print(f"frames {res['frames']}  wrong {res['wrong']}  refused {res['refused']}  right {res['right']}  "
          f"wrong rate 95 % [{low:.2e}, {high:.2e}]  right rate {res['right_rate']:.3f}  largest attitude error of "
          f"a right frame {res['max_right_error_deg']:.3f} deg  {res['wall_s']} s")
    if args.out:
        Path(args.out).write_text(json.dumps(res, indent=1) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
