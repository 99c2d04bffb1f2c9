"""One sample drawn from the simulator: a frame of head 0 rendered by :class:`~starenv.sim.sensor.StarSensor` at a drawn
attitude and rate, with its labels.

Sample ``i`` of a spec is a pure function of (spec, ``i``): ``np.random.SeedSequence([spec.seed, i]).spawn(2)``
gives the stream of the draws (attitude, rates, randomised overrides, star edits, in that order) and the sensor's
noise seed.  The scenario's motion is replaced by a constant rate, and its initial attitude chosen so that the drawn
attitude holds at head 0's mid-exposure of frame 0 (for ``main_star``: the navigation star sits on the boresight at
mid-exposure, its trail centred on the image centre; with ``pointing.offset_deg`` the boresight is drawn about it
instead, uniformly in the cap of that radius among the directions whose nearest navigation star it is, so the label
is the navigation star nearest the image centre, the paper's main star).  A ``main_star`` image is the frame as the
network reads it (:func:`starenv.datasets.preprocess.network_input`: area-resized to ``input_size``, background
subtracted; with ``centre = "main_star"`` shifted to put the main star's mid-exposure position, projected through
head 0's camera, at its centre).  With ``readout = "binned"`` the sensor draws the frame's block means directly
(:meth:`~starenv.sim.imager.Detector.read_out_binned`) instead of reading the whole frame out and resizing it.

The scenario is parsed and validated once per process and spec (:func:`context`); a sample replaces only its motion
(:func:`starenv.scenario.with_motion`) and reloads the scenario only when the spec randomises other keys.

Rates are drawn in head 0's camera frame (+Z boresight):
``(r cos a, r sin a, roll rate)`` with ``r`` the two-axis resultant and ``a`` the smear direction, and turned into
the body frame through the mounting.

Star edits act on the sky the sensor renders (a cone about the boresight): ``missing`` removes 1..max_changed stars
that fall in the frame (never the main star), ``false`` adds 1..max_changed stars at uniform pixel positions with
magnitudes uniform in ``false_mag_range`` (HIP id -1); position noise shifts each star's direction (its whole trail)
by a Gaussian of ``position_sigma_px`` px per axis at head 0's plate scale; magnitude noise adds a Gaussian to Hp.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from starenv import scenario as scenario_mod
from starenv.datasets.pairs import attitude_pairs
from starenv.datasets.preprocess import network_input, square_block
from starenv.datasets.smear import sharp_reference
from starenv.datasets.spec import VARIANTS, DatasetSpec
from starenv.sim.conventions import DEG, frame_span_s, pointing, radec_to_unit, unit_to_radec
from starenv.sim.sensor import StarSensor
from starenv.sim.sky import StarCatalog, load_catalog

COMMON_FIELDS = ("attitude", "rate_dps", "variant")
# per kind: the fields with one row per star (concatenated over a shard's samples, ``count`` stars each) and the
# fields with one entry per sample (stacked)
FIELDS = {
    "main_star": ((), ("image", "label", "hip", *COMMON_FIELDS)),
    "centroids": (("xy", "catalog_id", "magnitude"), ("count", *COMMON_FIELDS)),
    "position_pairs": (("catalog_id", "measured", "distorted", "reference"), ("count", *COMMON_FIELDS)),
    "smear_pairs": (("smeared", "sharp", "origin", "xy_mid", "catalog_id"), ("count", "exposure_s", *COMMON_FIELDS)),
}


@functools.lru_cache(maxsize=8)
def _navigation(mag_limit: float, epoch: float, ra_deg: float, dec_deg: float, radius_deg: float):
    cat = load_catalog(mag_limit, epoch)
    rows = cat.cone(radec_to_unit(np.radians(ra_deg), np.radians(dec_deg)), np.radians(radius_deg))
    return cat.hip[rows].copy(), cat.unit[rows].copy()


@dataclass(frozen=True)
class SampleContext:
    """What every sample of a spec shares, built once per process: the scenario with the spec's fixed overrides
    (parsed and validated), the classes (HIP, ICRS units) and every navigation star of the sky (Hp <=
    ``pointing.mag_limit``, for the nearest-star rule of off-centre boresights)."""

    scenario: scenario_mod.Scenario
    classes_hip: np.ndarray
    classes_unit: np.ndarray
    sky_hip: np.ndarray
    sky_tree: object  # scipy cKDTree of the sky's units


_CONTEXTS: dict[str, SampleContext] = {}
MAX_CONTEXTS = 4  # specs whose context one process keeps (a build uses one; tests and benchmarks a few)


def context(spec: DatasetSpec) -> SampleContext:
    """The :class:`SampleContext` of ``spec`` (cached by the spec's digest in this process)."""
    key = spec.digest
    if key not in _CONTEXTS:
        sc = spec.load_scenario()
        p = spec.pointing
        hip, unit = _navigation(p.mag_limit, sc.epoch, p.center_ra_deg, p.center_dec_deg, p.radius_deg)
        sky = load_catalog(p.mag_limit, sc.epoch)
        while len(_CONTEXTS) >= MAX_CONTEXTS:
            _CONTEXTS.pop(next(iter(_CONTEXTS)))
        _CONTEXTS[key] = SampleContext(sc, hip, unit, sky.hip, sky.tree)
    return _CONTEXTS[key]


def navigation_stars(spec: DatasetSpec) -> tuple[np.ndarray, np.ndarray]:
    """The classes of a ``main_star`` spec: HIP numbers (sorted; the label is the index) and ICRS unit vectors of the
    stars with Hp <= ``pointing.mag_limit`` within ``pointing.radius_deg`` of the pointing centre."""
    ctx = context(spec)
    return ctx.classes_hip, ctx.classes_unit


OFFSET_TRIES = 64  # boresights drawn at once about the main star; the first whose nearest navigation star it is wins
MAX_OFFSET_ROUNDS = 1000  # then the boresight stays on the star (a cell smaller than any drawn cap allows)


def _off_centre(ctx: SampleContext, main: int, offset_deg: float, rng: np.random.Generator) -> np.ndarray:
    """A boresight (ICRS unit) uniform in the cap of ``offset_deg`` about class ``main`` among the directions whose
    nearest navigation star is that star (rejection: ``OFFSET_TRIES`` cap draws a round)."""
    star = ctx.classes_unit[main]
    e1 = np.cross([0.0, 0.0, 1.0], star)
    if np.linalg.norm(e1) < 1e-9:
        e1 = np.array([1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(star, e1)
    hip = ctx.classes_hip[main]
    for _ in range(MAX_OFFSET_ROUNDS):
        u = rng.random((OFFSET_TRIES, 2))
        cos_t = 1.0 - u[:, 0] * (1.0 - np.cos(offset_deg * DEG))  # uniform in the cap's solid angle
        sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t**2))
        phi = 2.0 * np.pi * u[:, 1]
        axes = cos_t[:, None] * star + sin_t[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
        nearest = ctx.sky_hip[ctx.sky_tree.query(axes)[1]]
        hit = np.flatnonzero(nearest == hip)
        if len(hit):
            return axes[hit[0]] / np.linalg.norm(axes[hit[0]])
    return star


def _initial_pointing(att_mid: Rotation, rate_body: np.ndarray, t_mid: float, mounting: Rotation) -> dict:
    """The scenario's ``motion`` table: constant body rate, initial attitude so that ``att_mid`` holds at ``t_mid``.

    ``ConstantRate.delta(t) = Rotation.from_rotvec(-rate t)`` and attitude(t) = delta(t) * initial."""
    initial = Rotation.from_rotvec(rate_body * t_mid) * att_mid
    cam0 = mounting * initial
    ra, dec = unit_to_radec(cam0.as_matrix()[2])
    roll = -(cam0 * pointing(float(ra), float(dec), 0.0).inv()).as_rotvec()[2]
    return {"kind": "constant_rate", "rate_dps": [float(x) for x in rate_body / DEG],
            "initial_ra_deg": float(np.degrees(ra)), "initial_dec_deg": float(np.degrees(dec)),
            "initial_roll_deg": float(np.degrees(roll))}


def draw(spec: DatasetSpec, index: int) -> dict:
    """The sample's drawn parameters: ``main`` (class index, -1 for uniform pointing), ``attitude`` (inertial -> body
    Rotation at mid-exposure), ``rate_cam_dps`` (3,), ``variant``, ``changed`` (stars edited), ``randomized``
    (scenario overrides) and ``seeds`` (the two SeedSequences: draws, sensor noise)."""
    seeds = np.random.SeedSequence([spec.seed, index]).spawn(2)
    rng = np.random.default_rng(seeds[0])
    ctx = context(spec)
    mounting = ctx.scenario.heads[0].camera.mounting
    p, r = spec.pointing, spec.rates
    if p.mode == "main_star":
        hip, unit = ctx.classes_hip, ctx.classes_unit
        main = int(rng.integers(len(hip)))
        step = p.roll_step_deg
        roll = float(rng.integers(round(360.0 / step))) * step if step > 0 else float(rng.uniform(0.0, 360.0))
        boresight = unit[main] if p.offset_deg == 0.0 else _off_centre(ctx, main, p.offset_deg, rng)
        ra, dec = unit_to_radec(boresight)
        cam = pointing(float(ra), float(dec), roll * DEG)
    else:
        main = -1
        cam = Rotation.random(random_state=rng)
    if r.two_axis_range_dps is not None:
        magnitude = float(rng.uniform(*r.two_axis_range_dps))
    else:
        magnitude = float(r.two_axis_dps[rng.integers(len(r.two_axis_dps))])
    angle = float(rng.integers(r.directions)) * 360.0 / r.directions if r.directions else float(rng.uniform(0, 360))
    roll_rate = float(r.roll_dps[rng.integers(len(r.roll_dps))])
    rate_cam = np.array([magnitude * np.cos(angle * DEG), magnitude * np.sin(angle * DEG), roll_rate])
    randomized = {key: float(rng.uniform(lo, hi)) for key, (lo, hi) in spec.randomize.items()}
    variant = spec.stars.variants[rng.integers(len(spec.stars.variants))]
    changed = 0 if variant == "clean" else int(rng.integers(1, spec.stars.max_changed + 1))
    return {"main": main, "attitude": mounting.inv() * cam, "rate_cam_dps": rate_cam, "variant": variant,
            "changed": changed, "randomized": randomized, "rng": rng, "sensor_seed": seeds[1]}


def motion_table(base: scenario_mod.Scenario, params: dict) -> dict:
    """The scenario ``[motion]`` table of drawn ``params`` (see :func:`draw`): their constant rate, and the initial
    attitude that puts ``params["attitude"]`` at head 0's mid-exposure of frame 0."""
    head = base.heads[0]
    cam = head.camera
    t_mid = 0.5 * frame_span_s(base.exposure_s, head.detector.line_time_s, cam.height)
    rate_body = cam.mounting.inv().apply(np.asarray(params["rate_cam_dps"], dtype=np.float64) * DEG)
    return _initial_pointing(params["attitude"], rate_body, t_mid, cam.mounting)


def render(spec: DatasetSpec, params: dict) -> tuple[StarSensor, object]:
    """Render frame 0 of head 0 for drawn ``params`` (see :func:`draw`): the sensor and its :class:`Frame`."""
    rng = params["rng"]
    base = spec.load_scenario(params["randomized"]) if params["randomized"] else context(spec).scenario
    sc = scenario_mod.with_motion(base, motion_table(base, params))
    catalog = _edited_sky(spec, sc, params, rng)
    cam = sc.heads[0].camera
    block = square_block(cam.width, cam.height, spec.input_size) if spec.readout == "binned" else 1
    sensor = StarSensor(sc, catalog=catalog, readout_block=block)
    sensor.reset(params["sensor_seed"])
    return sensor, sensor.next_frame()


def _edited_sky(spec: DatasetSpec, sc, params: dict, rng: np.random.Generator) -> StarCatalog:
    """The sky about head 0's boresight with the sample's star edits and noise (see the module docstring)."""
    full = load_catalog(sc.mag_limit, sc.epoch)
    cam = sc.heads[0].camera
    cam_rot = cam.inertial_to_camera(params["attitude"])
    boresight = cam_rot.inv().apply([0.0, 0.0, 1.0])
    smear = np.linalg.norm(params["rate_cam_dps"]) * DEG * sc.exposure_s
    rows = full.cone(boresight, min(np.pi, cam.half_diagonal + smear + 0.5 * DEG))
    hip, mag, unit = full.hip[rows].copy(), full.magnitude[rows].copy(), full.unit[rows].copy()
    st = spec.stars
    if params["variant"] == "missing" and len(hip):
        xy, in_front = cam.project(cam_rot.apply(unit))
        inside = in_front & cam.in_frame(xy)
        if params["main"] >= 0:
            inside &= hip != navigation_stars(spec)[0][params["main"]]
        candidates = np.flatnonzero(inside)
        drop = rng.choice(candidates, size=min(params["changed"], len(candidates)), replace=False)
        keep = np.setdiff1d(np.arange(len(hip)), drop)
        hip, mag, unit = hip[keep], mag[keep], unit[keep]
    if params["variant"] == "false":
        n = params["changed"]
        xy = np.column_stack([rng.uniform(-0.5, cam.width - 0.5, n), rng.uniform(-0.5, cam.height - 0.5, n)])
        fake_unit = cam_rot.inv().apply(cam.unproject(xy))
        hip = np.concatenate([hip, np.full(n, -1, dtype=np.int64)])
        mag = np.concatenate([mag, rng.uniform(*st.false_mag_range, n)])
        unit = np.vstack([unit, fake_unit])
    if st.position_sigma_px > 0 and len(hip):
        e1 = np.cross(unit, [0.0, 0.0, 1.0])
        e1[np.linalg.norm(e1, axis=1) < 1e-9] = [1.0, 0.0, 0.0]
        e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
        e2 = np.cross(unit, e1)
        shift = rng.normal(0.0, st.position_sigma_px / cam.fx, (len(hip), 2))
        unit = unit + shift[:, :1] * e1 + shift[:, 1:] * e2
        unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    if st.magnitude_sigma > 0 and len(hip):
        mag = mag + rng.normal(0.0, st.magnitude_sigma, len(hip))
    return StarCatalog(hip=hip, magnitude=mag, unit=unit, epoch=full.epoch)


def sample(spec: DatasetSpec, index: int) -> dict[str, np.ndarray]:
    """Sample ``index`` of ``spec`` as arrays (fields: ``FIELDS[spec.kind]``).

    ``position_pairs``: per star seen by head 0 at the drawn attitude, ``catalog_id``, ``measured`` (the true optics'
    position plus ``pairs.centroid_noise_px`` of Gaussian noise), ``distorted`` (noise-free) and ``reference`` (the
    calibrated camera's position of the same direction), px; no image is rendered (:mod:`starenv.datasets.pairs`).
    ``smear_pairs``: per detectable star whose ``patches.size_px`` square patch about its mid-exposure pixel lies on
    the frame, the patch of the smeared frame (uint16 DN) and of its sharp reference (float32 DN above bias, no
    background: :func:`starenv.datasets.smear.sharp_reference`), the patch's ``origin`` (x, y) and the star's
    ``xy_mid`` px.  ``attitude`` is a quaternion (x, y, z, w, inertial -> body), ``rate_dps`` head 0's camera-frame
    rate."""
    params = draw(spec, index)
    common = {
        "attitude": params["attitude"].as_quat().astype(np.float64),
        "rate_dps": np.asarray(params["rate_cam_dps"], dtype=np.float64),
        "variant": np.int8(VARIANTS.index(params["variant"])),
    }
    if spec.kind == "position_pairs":
        pairs = attitude_pairs(spec.load_scenario(params["randomized"]), params["attitude"], params["rng"],
                               spec.pairs.centroid_noise_px)
        return {"catalog_id": pairs.catalog_id.astype(np.int64), "measured": pairs.measured,
                "distorted": pairs.distorted, "reference": pairs.reference, "count": np.int32(len(pairs)), **common}
    sensor, frame = render(spec, params)
    head = frame.heads[0]
    if spec.kind == "smear_pairs":
        return {**_patches(head, sharp_reference(sensor, frame.t_mid), spec.patches.size_px),
                "exposure_s": np.float64(sensor.scenario.exposure_s), **common}
    if spec.kind == "main_star":
        hip = navigation_stars(spec)[0]
        centre = None
        if spec.centre == "main_star":
            cam = sensor.scenario.heads[0].camera
            star = navigation_stars(spec)[1][params["main"]]
            xy, _ = cam.project(cam.inertial_to_camera(params["attitude"]).apply(star[None]))
            block = cam.width / head.image.shape[1]  # 1, or the binned read-out's block
            centre = (xy[0] + 0.5) / block - 0.5
        return {"image": network_input(head.image, spec.input_size, centre), "label": np.int32(params["main"]),
                "hip": np.int64(hip[params["main"]]), **common}
    truth = head.truth
    keep = truth.detectable
    return {"xy": truth.xy_centroid[keep].astype(np.float64), "catalog_id": truth.catalog_id[keep].astype(np.int64),
            "magnitude": truth.magnitude[keep].astype(np.float64), "count": np.int32(keep.sum()), **common}


def _patches(head, sharp: np.ndarray, size: int) -> dict[str, np.ndarray]:
    """The smeared and sharp ``size`` x ``size`` patches about each detectable star of ``head`` that fit the frame."""
    truth = head.truth
    height, width = head.image.shape
    origin = np.rint(truth.xy_mid).astype(np.int64) - size // 2
    keep = truth.detectable & np.all(origin >= 0, axis=1) & (origin[:, 0] + size <= width) & (
        origin[:, 1] + size <= height)
    origin = origin[keep]
    rows = origin[:, 1, None] + np.arange(size)
    cols = origin[:, 0, None] + np.arange(size)
    return {"smeared": head.image[rows[:, :, None], cols[:, None, :]],
            "sharp": sharp[rows[:, :, None], cols[:, None, :]].astype(np.float32),
            "origin": origin, "xy_mid": truth.xy_mid[keep].astype(np.float64),
            "catalog_id": truth.catalog_id[keep].astype(np.int64), "count": np.int32(keep.sum())}
