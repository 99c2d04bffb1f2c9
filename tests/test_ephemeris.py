"""The ephemeris and stellar aberration against astropy (SOFA): the Earth's barycentric velocity, apparent star
directions (ICRS -> GCRS, geocentric and in orbit), rendered frames and the pipeline's correction."""

import warnings

import numpy as np
import pytest

from starenv import scenario as scenario_mod
from starenv.agents.pipeline import Pipeline
from starenv.env import StarSensorEnv
from starenv.sim import ephemeris
from starenv.sim.conventions import ARCSEC, ARCSEC_PER_RAD, DEG, radec_to_unit
from starenv.sim.sensor import StarSensor

astropy = pytest.importorskip("astropy")
from astropy import units as u  # noqa: E402
from astropy.coordinates import GCRS, ICRS, CartesianRepresentation, SkyCoord  # noqa: E402
from astropy.time import Time  # noqa: E402

C = ephemeris.C_M_S
# Light deflection by the Sun, which astropy applies and the simulator neglects: 4.07 mas cot(E / 2) at elongation E.
DEFLECTION_MAS = 4.07
MIN_ELONGATION_DEG = 20.0  # directions compared lie this far from the Sun: deflection <= 23 mas


def _jd(years):
    return ephemeris.J2000_JD + (np.asarray(years) - 2000.0) * 365.25


# The geocentre's barycentric velocity (m/s, ICRF) in JPL's DE421 (the `de421` package read with jplephem: the
# Earth-Moon barycentre's less the Moon's geocentric over 1 + M_earth / M_moon) at these TT Julian years.
DE421_YEARS = (1910.3, 1955.7, 1987.2, 2003.9, 2026.0, 2044.6)
DE421_EARTH_VELOCITY = ((14794.223, -23541.771, -10211.722), (4212.365, 26906.402, 11669.071),
                        (-3416.360, -27301.743, -11836.346), (-27085.723, 12218.365, 5297.907),
                        (-29776.506, -4950.769, -2146.230), (20499.712, 19265.443, 8349.508))


def test_earth_velocity_matches_jpl_de421():
    # epv00 is within 5 mm/s of DE405 over 1900-2100 (its documentation's worst case); the literals carry 1 mm/s.
    # A 0.02 m/s bound is 0.014 mas of aberration.
    ours = ephemeris.earth_velocity((np.array(DE421_YEARS) - 2000.0) / 100.0)
    assert np.abs(ours - np.array(DE421_EARTH_VELOCITY)).max() < 0.02


def test_relativistic_aberration_closed_form():
    # A source at angle theta from the velocity appears at theta' with cos theta' = (cos theta + b) / (1 + b cos theta)
    # (special relativity); at b = 0.5 the first-order formula is off by degrees.
    beta = 0.5
    theta = np.linspace(0.01, np.pi - 0.01, 50)
    directions = np.stack([np.cos(theta), np.sin(theta), np.zeros_like(theta)], axis=1)
    apparent = ephemeris.aberrate(directions, [beta * C, 0.0, 0.0])
    expected = np.arccos((np.cos(theta) + beta) / (1.0 + beta * np.cos(theta)))
    assert np.allclose(np.arctan2(apparent[:, 1], apparent[:, 0]), expected, atol=1e-12)
    assert np.allclose(apparent[:, 2], 0.0)
    with pytest.raises(ValueError, match="slower than light"):
        ephemeris.aberrate(directions, [C, 0.0, 0.0])


def _astropy_apparent(directions, year, obs_position_m=None, obs_velocity_m_s=None):
    """GCRS unit vectors of ICRS directions at TT Julian year ``year`` (optionally for an observer in orbit)."""
    time = Time(_jd(year), format="jd", scale="tt")
    kwargs = {}
    if obs_velocity_m_s is not None:
        kwargs["obsgeoloc"] = CartesianRepresentation(*obs_position_m, unit=u.m)
        kwargs["obsgeovel"] = CartesianRepresentation(*obs_velocity_m_s, unit=u.m / u.s)
    icrs = SkyCoord(CartesianRepresentation(*directions.T), frame=ICRS())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # ERFA's "dubious year" for UTC before 1960 / after the leap-second table
        gcrs = icrs.transform_to(GCRS(obstime=time, **kwargs))
    xyz = gcrs.cartesian.xyz.value.T
    return xyz / np.linalg.norm(xyz, axis=1, keepdims=True)


def _far_from_sun(directions, year):
    sun = ephemeris.body_geocentric("sun", (year - 2000.0) / 100.0)
    cos_e = directions @ (sun / np.linalg.norm(sun))
    return directions[cos_e < np.cos(MIN_ELONGATION_DEG * DEG)]


@pytest.mark.parametrize("in_orbit", [False, True])
def test_apparent_directions_match_astropy_gcrs(in_orbit):
    # Within 0.1 arcsec, and within what the model neglects: the solar deflection at 20 degrees or more from the Sun
    # (23 mas), plus 1 mas for the velocity (astropy's is epv00's too; the orbit's velocity is added as a vector, the
    # relativistic composition differing by ~1e-8 of v: 0.2 mas).  The aberration itself is ~20 arcsec (~25 in orbit).
    rng = np.random.default_rng(1)
    worst = 0.0
    for year in rng.uniform(*ephemeris.EPHEMERIS_YEARS, 12):
        directions = rng.normal(size=(200, 3))
        directions = _far_from_sun(directions / np.linalg.norm(directions, axis=1, keepdims=True), year)
        velocity = ephemeris.observer_velocity(year, 0.0)
        position = orbit_velocity = None
        if in_orbit:
            position = 6.9e6 * radec_to_unit(*rng.uniform([0, -1.2], [6.28, 1.2]))
            normal = np.cross(position, rng.normal(size=3))
            orbit_velocity = 7.6e3 * normal / np.linalg.norm(normal)
            velocity = ephemeris.observer_velocity(year, 0.0, lambda _t, v=orbit_velocity: v)
        ours = ephemeris.aberrate(directions, velocity)
        reference = _astropy_apparent(directions, year, position, orbit_velocity)
        error = np.arccos(np.clip(np.sum(ours * reference, axis=1), -1.0, 1.0)) * ARCSEC_PER_RAD
        shift = np.arccos(np.clip(np.sum(ours * directions, axis=1), -1.0, 1.0)) * ARCSEC_PER_RAD
        assert shift.max() > 15.0  # the effect is there
        worst = max(worst, float(error.max()))
    deflection_arcsec = DEFLECTION_MAS / np.tan(np.radians(MIN_ELONGATION_DEG) / 2.0) / 1000.0
    assert worst < min(0.1, 0.001 + deflection_arcsec)


def test_rendered_stars_sit_at_astropy_apparent_directions_in_orbit():
    # The frame's truth positions, taken back through the true camera at the true attitude, are the stars' apparent
    # directions for the orbit's velocity: bound 0.1 arcsec as above (the Newton inversion of the distortion adds
    # < 1e-9 px).
    sc = scenario_mod.load("leo_distortion", {"sky.aberration": True})
    sensor = StarSensor(sc)
    frame = sensor.next_frame()
    truth = frame.heads[0].truth
    cam = sc.heads[0].camera
    camera_dirs = cam.unproject(truth.xy_mid)
    icrs_dirs = (cam.inertial_to_camera(frame.attitude)).inv().apply(camera_dirs)
    rows = np.searchsorted(sensor.catalog.hip, truth.catalog_id)
    orbit = sc.trajectory.orbit
    reference = _astropy_apparent(sensor.catalog.unit[rows], sc.epoch + frame.t_mid / (86400 * 365.25),
                                  orbit.position(frame.t_mid), orbit.velocity(frame.t_mid))
    error = np.arccos(np.clip(np.sum(icrs_dirs * reference, axis=1), -1.0, 1.0)) * ARCSEC_PER_RAD
    geometric = np.arccos(np.clip(np.sum(icrs_dirs * sensor.catalog.unit[rows], axis=1), -1, 1)) * ARCSEC_PER_RAD
    assert len(error) > 20 and error.max() < 0.1 and geometric.min() > 5.0
    assert np.allclose(frame.observer_velocity_m_s, ephemeris.observer_velocity(sc.epoch, frame.t_mid, orbit.velocity))


def _mean_cross_boresight_error(correct_aberration: bool, steps: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Mean signed attitude error (arcsec) about camera +X and +Y of the built-in pipeline on a still paper_000
    pointing with aberration, and the bias the uncorrected solution should show there."""
    env = StarSensorEnv("paper_000", {"sky.aberration": True, "motion.rate_dps": [0.0, 0.0, 0.0]})
    pipeline = Pipeline(correct_aberration=correct_aberration)
    obs, info = env.reset(seed=0)
    pipeline.reset(env.unwrapped.sensor_info)
    errors = []
    for _ in range(steps):
        obs_velocity = obs["observer_velocity_m_s"]
        obs, _, _, _, info = env.step(pipeline(obs))
        head = info["scores"]["attitude"]["heads"][0]
        errors.append([head["x_arcsec"], head["y_arcsec"]])
    # Uncorrected, the solver rotates the catalogue onto the apparent sky: about the boresight p by the rotation
    # taking p to its apparent direction, p x (beta - (p . beta) p) = p x beta to first order in v/c, across the
    # boresight (the roll, poorly observed in a narrow field, is left out).
    sc = env.unwrapped.scenario
    to_camera = sc.heads[0].camera.inertial_to_camera(sc.trajectory.attitude(0.0))
    boresight = to_camera.inv().apply([0.0, 0.0, 1.0])
    expected = to_camera.apply(np.cross(boresight, obs_velocity / C))[:2] / ARCSEC
    return np.mean(errors, axis=0), expected


def test_pipeline_correction_removes_the_aberration_bias():
    # Each frame's cross-boresight noise is ~1 arcsec (centroids of ~0.05 px at 84 arcsec/px over ~20 stars): the
    # mean of 8 frames is within 1.5 arcsec of truth.  Uncorrected, on the same frames (same seed), the solution moves
    # by (v/c) sin(angle of the boresight to the velocity), ~20 arcsec; the field's curvature changes that by a
    # fraction ~ (field radius)^2 ~ 1e-2, hence 0.02 of it plus 0.1 arcsec of solver tolerance.
    corrected, expected = _mean_cross_boresight_error(True)
    uncorrected, _ = _mean_cross_boresight_error(False)
    assert np.linalg.norm(expected) > 15.0
    assert np.linalg.norm(corrected) < 1.5
    assert np.linalg.norm(uncorrected - corrected - expected) < 0.1 + 0.02 * np.linalg.norm(expected)


def test_aberration_is_off_by_default_and_the_epoch_is_checked():
    sc = scenario_mod.load("paper_000")
    assert not sc.sky.aberration and StarSensor(sc).next_frame().observer_velocity_m_s.tolist() == [0.0] * 3
    with pytest.raises(scenario_mod.ScenarioError, match=r"paper_000.toml: epoch: expected an epoch .* 1900-2100"):
        scenario_mod.load("paper_000", {"sky.aberration": True, "epoch": 2100.0})
    with pytest.raises(scenario_mod.ScenarioError, match=r"sky.aberration.*expected true or false"):
        scenario_mod.load("paper_000", {"sky.aberration": 1})
