"""Scenario loader: the bundled files carry their papers' values, every invalid key raises one ScenarioError naming
the file, the dotted key path and the expected form, overrides edit the parsed file, ``to_toml`` round-trips,
sequences and jitter load into continuous motions, and fuzzed dicts / files never escape as another exception."""

from __future__ import annotations

import copy
import math
import re
import tempfile
import tomllib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from starenv.scenario import SCENARIO_DIR, AvailabilityThreshold, Scenario, ScenarioError, bundled_names, load
from starenv.sim.conventions import DEG, angle_between, pointing, unit_to_radec
from starenv.sim.motion import ConstantRate, LeoNadir, Sequence, Superposed, TorqueFree
from starenv.sim.optics import Camera, LegendreField, NoDistortion, RadialXY

BUNDLED = bundled_names()
PAPERS = [f"paper_{i:03d}" for i in range(5)]
Z = np.array([0.0, 0.0, 1.0])


def parsed(name: str) -> dict:
    """A bundled scenario's TOML, parsed."""
    return tomllib.loads((SCENARIO_DIR / f"{name}.toml").read_text(encoding="utf-8"))


def boresight_radec_deg(camera, attitude) -> tuple[float, float]:
    """RA, Dec (deg) of a head's boresight for a body attitude (inertial -> body)."""
    b = camera.inertial_to_camera(attitude).inv().apply(Z)
    ra, dec = unit_to_radec(b)
    return float(np.degrees(ra)), float(np.degrees(dec))


def body_boresight(camera) -> np.ndarray:
    """A head's boresight in body coordinates."""
    return camera.mounting.inv().apply(Z)


def full_fov_deg(extent_px: int, pitch_m: float, focal_m: float) -> float:
    """Edge-to-edge field of view of a sensor side, from the physical values."""
    return math.degrees(2.0 * math.atan(extent_px * pitch_m / (2.0 * focal_m)))


def located(source: str, key: str, *expected: str) -> str:
    """Regex for '<source>: <key>: ...<expected pieces in order>'."""
    return re.escape(f"{source}: {key}: ") + ".*" + ".*".join(re.escape(e) for e in expected)


def bundled_file(name: str) -> str:
    return str(SCENARIO_DIR / f"{name}.toml")


# ---------------------------------------------------------------------------------------------------------------
# Bundled scenarios against the values their header comments quote from the papers.


def test_all_papers_and_stress_cases_are_bundled():
    # One scenario per source paper plus the stress cases: a renamed or lost file fails here.
    assert set(PAPERS + ["stress_drops", "stress_stray_light", "stress_tumble"]) <= set(BUNDLED)
    assert BUNDLED == sorted(BUNDLED)


@pytest.mark.parametrize("name", BUNDLED)
def test_every_bundled_scenario_loads(name):
    # Each bundled file validates, keeps its name and source, and has consistent timing.
    sc = load(name)
    assert isinstance(sc, Scenario)
    assert sc.name == name
    assert sc.source == bundled_file(name)
    assert sc.heads and sc.description
    assert 0 < sc.exposure_s <= sc.frame_period_s
    assert sc.n_steps == round(sc.duration_s * sc.frame_rate_hz)
    assert load(Path(bundled_file(name))).name == name  # by path as well as by name


def test_paper_000_camera():
    # 49 mm / 20 um = 2450 px; 512 x 512 crop = 11.9 deg; f/1.2 -> 40.8 mm pupil; 10 ms at 100 Hz for 15 s.
    sc = load("paper_000")
    cam = sc.heads[0].camera
    assert cam.fx == pytest.approx(2450.0) and cam.fy == pytest.approx(2450.0)
    assert (cam.width, cam.height) == (512, 512)
    assert (cam.cx, cam.cy) == (255.5, 255.5)
    assert cam.pixel_pitch_m == pytest.approx(20e-6)
    assert cam.aperture_m == pytest.approx(49e-3 / 1.2)
    assert math.degrees(cam.fov[0]) == pytest.approx(11.9, abs=0.05)
    assert sc.exposure_s == 0.01 and sc.frame_rate_hz == 100.0 and sc.n_steps == 1500
    assert cam.distortion == RadialXY(kx=2.0e-8, ky=1.5e-8)
    assert sc.heads[0].calibrated is cam  # no [heads.calibration]: the sensor knows the truth
    assert sc.heads[0].detector.adc_bits == 12 and sc.heads[0].psf_sigma_px == 0.8
    np.testing.assert_allclose(sc.trajectory.body_rate(0.0), np.array([1.0, 1.0, 1.0]) * DEG)
    assert boresight_radec_deg(cam, sc.trajectory.attitude(0.0)) == pytest.approx((83.8, -5.4))


def test_paper_001_camera():
    # 800 x 600 px of 7.86 um behind 60 mm: 6 x 4.5 deg; 60 ms exposure; 2.5 deg/s.
    sc = load("paper_001")
    cam = sc.heads[0].camera
    assert (cam.width, cam.height) == (800, 600)
    assert cam.fx == pytest.approx(60.0 / 7.86e-3)
    assert math.degrees(cam.fov[0]) == pytest.approx(6.0, abs=0.01)
    assert math.degrees(cam.fov[1]) == pytest.approx(4.5, abs=0.01)
    assert full_fov_deg(800, 7.86e-6, 60e-3) == pytest.approx(math.degrees(cam.fov[0]))
    assert sc.exposure_s == 0.06 and sc.mag_limit == 7.0
    assert np.linalg.norm(sc.trajectory.body_rate(0.0)) == pytest.approx(2.5 * DEG)
    assert isinstance(cam.distortion, NoDistortion)
    # Availability per axis, roll bound from the field: roll error ~ cross-boresight error x focal / half the 6 deg
    # side, both in px (the file rounds the product to the arcsec).
    threshold = sc.availability_threshold_arcsec
    assert threshold.total_arcsec is None and threshold.cross_boresight_arcsec == 60.0
    assert threshold.roll_arcsec == pytest.approx(60.0 * cam.fx / (cam.width / 2), abs=0.5)


def test_an_availability_threshold_is_one_number_or_a_table_of_both_axes():
    assert load("paper_000").availability_threshold_arcsec == AvailabilityThreshold(total_arcsec=100.0)
    table = load("paper_000", {"availability_threshold_arcsec": {"roll": 500, "cross_boresight": 12.5}})
    assert table.availability_threshold_arcsec == AvailabilityThreshold(cross_boresight_arcsec=12.5, roll_arcsec=500.0)
    edited = load("paper_001", {"availability_threshold_arcsec.roll": 900.0}).availability_threshold_arcsec
    assert (edited.cross_boresight_arcsec, edited.roll_arcsec) == (60.0, 900.0)
    again = load(tomllib.loads(table.to_toml()))
    assert again.availability_threshold_arcsec == table.availability_threshold_arcsec


def test_paper_002_camera():
    # 1024^2 px of 12 um behind 58.5 mm: 12 x 12 deg; 92 ms in a 100 ms frame; 5 deg/s resultant.
    sc = load("paper_002")
    cam = sc.heads[0].camera
    assert (cam.width, cam.height) == (1024, 1024)
    assert sc.exposure_s == 0.092 and sc.frame_period_s == pytest.approx(0.1)
    assert cam.fx == pytest.approx(4875.0)
    assert [math.degrees(a) for a in cam.fov] == pytest.approx([12.0, 12.0], abs=0.02)
    assert sc.heads[0].psf_sigma_px == 1.0 and sc.mag_limit == 6.5
    assert np.linalg.norm(sc.trajectory.body_rate(0.0)) == pytest.approx(5.0 * DEG, rel=0.01)


def test_paper_003_leo_nadir_with_uncalibrated_legendre_distortion():
    # 2048^2 px of 7.45 um, 43.2 mm: 20 deg; LEO 550 km, 53 deg, 1 frame/s; true Legendre field, calibration none.
    sc = load("paper_003")
    head = sc.heads[0]
    cam = head.camera
    assert (cam.width, cam.height) == (2048, 2048)
    assert cam.fx == pytest.approx(43.2 / 7.45e-3)
    assert math.degrees(cam.fov[0]) == pytest.approx(20.0, abs=0.05)
    assert sc.frame_rate_hz == 1.0
    motion = sc.trajectory.motion
    assert isinstance(motion, LeoNadir)
    assert motion.altitude == pytest.approx(550e3)
    assert motion.inclination == pytest.approx(53.0 * DEG)
    assert motion.period == pytest.approx(5739.0, rel=1e-3)  # 2 pi sqrt(a^3 / mu), a = 6928 km
    # The true camera has the Legendre field, what the sensor believes has none; everything else is shared.
    assert isinstance(cam.distortion, LegendreField) and cam.distortion.order == 3
    assert isinstance(head.calibrated.distortion, NoDistortion)
    assert (head.calibrated.fx, head.calibrated.cx, head.calibrated.width) == (cam.fx, cam.cx, cam.width)
    # "about 2 px at the edge of the image".
    edge = np.array([[0, 1023.5], [2047, 1023.5], [1023.5, 0], [1023.5, 2047], [0, 0], [2047, 2047]])
    shift = np.linalg.norm(cam.distortion.distort(edge, cam.intrinsics) - edge, axis=1)
    assert 1.0 < shift.max() < 3.5
    # Zenith camera: boresight body -Z, i.e. along the orbit radius at t = 0.
    np.testing.assert_allclose(body_boresight(cam), [0.0, 0.0, -1.0], atol=1e-12)
    zenith = motion.position(0.0) / np.linalg.norm(motion.position(0.0))
    np.testing.assert_allclose(cam.inertial_to_camera(sc.trajectory.attitude(0.0)).inv().apply(Z), zenith, atol=1e-9)


def test_paper_004_three_orthogonal_heads():
    # Three 6 deg heads (512^2 px of 8 um, 39.078 mm) with body boresights +Z, -X, -Y.
    sc = load("paper_004")
    assert len(sc.heads) == 3
    expected = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]
    for head, axis in zip(sc.heads, expected, strict=True):
        cam = head.camera
        assert (cam.width, cam.height) == (512, 512)
        assert math.degrees(cam.fov[0]) == pytest.approx(6.0, abs=0.01)
        assert cam.fx == pytest.approx(39.078 / 8e-3)
        np.testing.assert_allclose(body_boresight(cam), axis, atol=1e-12)
    assert [h.name for h in sc.heads] == ["fov1", "fov2", "fov3"]


def test_stress_scenarios():
    # Stress cases: ~20 % bursty drops in ~8-frame spells, Sun glow 25 deg off axis, ~30 deg/s tumble.
    drops = load("stress_drops").drops
    assert drops.drop_rate == pytest.approx(0.2, abs=0.01)
    assert 1.0 / drops.p_bad_to_good == 8.0
    stray = load("stress_stray_light").heads[0]
    assert stray.stray_light.off_axis_deg == 25.0 and stray.detector.cosmic_ray_rate_per_cm2_s == 200.0
    tumble = load("stress_tumble")
    assert isinstance(tumble.trajectory.motion, TorqueFree)
    assert math.degrees(np.linalg.norm(tumble.trajectory.body_rate(0.0))) == pytest.approx(30.0, abs=1.0)
    assert tumble.gyro.rate_hz == 1000.0


def test_stress_drops_slew_ends_on_its_target():
    # A slew's target is head 0's boresight: after the manoeuvre it looks at (100, 5).
    sc = load("stress_drops")
    motion = sc.trajectory.motion
    cam = sc.heads[0].camera
    assert boresight_radec_deg(cam, sc.trajectory.attitude(0.0)) == pytest.approx((83.8, -5.4))
    assert boresight_radec_deg(cam, sc.trajectory.attitude(motion.duration + 1.0)) == pytest.approx((100.0, 5.0))
    assert motion.start == 0.5


# ---------------------------------------------------------------------------------------------------------------
# Validation: one ScenarioError per problem, naming the file, the dotted key and the expected form.

P0 = bundled_file("paper_000")
P1 = bundled_file("paper_001")
P3 = bundled_file("paper_003")
P4 = bundled_file("paper_004")
TUMBLE = bundled_file("stress_tumble")
NAN, INF = float("nan"), float("inf")

INVALID = {
    "unknown top-level key": ("paper_000", {"colour": "red"}, located(P0, "colour", "unknown key", "exposure_s")),
    "unknown detector key": (
        "paper_000", {"heads.0.detector.gain_dn_per_e": 2.0},
        located(P0, "heads.0.detector.gain_dn_per_e", "unknown key", "gain_e_per_dn"),
    ),
    "unknown motion key": ("paper_000", {"motion.rate_rps": [0, 0, 1]}, located(P0, "motion.rate_rps", "unknown key")),
    "string for a number": ("paper_000", {"exposure_s": "10 ms"}, located(P0, "exposure_s", "a number", "'10 ms'")),
    "bool for a number": ("paper_000", {"mag_limit": True}, located(P0, "mag_limit", "a number in [-2, 12]", "True")),
    "bool for an integer": ("paper_000", {"heads.0.width": True}, located(P0, "heads.0.width", "an integer", "True")),
    "float for an integer": ("paper_000", {"heads.0.width": 512.5}, located(P0, "heads.0.width", "an integer")),
    "bool in a vector": (
        "paper_000", {"motion.rate_dps": [1.0, True, 0.0]}, located(P0, "motion.rate_dps", "a list of 3 numbers"),
    ),
    "short vector": ("paper_000", {"motion.rate_dps": [1.0, 2.0]}, located(P0, "motion.rate_dps", "3 numbers")),
    "table for a number": ("paper_000", {"seed": {"a": 1}}, located(P0, "seed", "an integer")),
    "string for a table": ("paper_000", {"gyro": "fog"}, located(P0, "gyro", "a table", "'fog'")),
    "negative exposure": ("paper_000", {"exposure_s": -0.01}, located(P0, "exposure_s", "(0, 0.01]", "-0.01")),
    "exposure past the frame period": (
        "paper_000", {"exposure_s": 0.02}, located(P0, "exposure_s", "in (0, 0.01]", "0.02"),
    ),
    "rolling readout past the frame period": (
        "paper_000", {"heads.0.detector.line_time_s": 1e-4}, located(P0, "exposure_s", "rolling-shutter readout"),
    ),
    "FOV of 180 deg": ("paper_000", {"heads.0.focal_length_mm": 1e-3}, located(P0, "heads.0", "field of view", "180")),
    "adc_bits = 0": (
        "paper_000", {"heads.0.detector.adc_bits": 0}, located(P0, "heads.0.detector.adc_bits", "integer in [1, 16]"),
    ),
    "adc_bits = 17": ("paper_000", {"heads.0.detector.adc_bits": 17}, located(P0, "heads.0.detector.adc_bits", "17")),
    "negative gain": (
        "paper_000", {"heads.0.detector.gain_e_per_dn": -5.0}, located(P0, "heads.0.detector.gain_e_per_dn", "[0.001,"),
    ),
    "NaN exposure": ("paper_000", {"exposure_s": NAN}, located(P0, "exposure_s", "a number", "nan")),
    "NaN in a vector": ("paper_000", {"motion.rate_dps": [0.0, NAN, 0.0]}, located(P0, "motion.rate_dps", "numbers")),
    "inf gyro noise": ("paper_000", {"gyro.arw_deg_rthr": INF}, located(P0, "gyro.arw_deg_rthr", "a number", "inf")),
    "gyro rate out of range": ("paper_000", {"gyro.rate_hz": 50.0}, located(P0, "gyro.rate_hz", "[100, 1000]")),
    "int too large for a float": ("paper_000", {"heads.0.height": 10**400}, located(P0, "heads.0.height", "integer")),
    "drop probability 1.5": (
        "paper_000", {"drops.probability": 1.5}, located(P0, "drops.probability", "[0, 1]", "1.5"),
    ),
    "declination 91": ("paper_000", {"motion.initial_dec_deg": 91}, located(P0, "motion.initial_dec_deg", "[-90, 90]")),
    "unknown motion kind": (
        "paper_000", {"motion.kind": "wobble"}, located(P0, "motion.kind", "one of 'constant_rate'", "'wobble'"),
    ),
    "unknown distortion kind": (
        "paper_000", {"heads.0.distortion.kind": "fisheye"},
        located(P0, "heads.0.distortion.kind", "one of 'none', 'brown_conrady', 'radial_xy', 'legendre'", "fisheye"),
    ),
    "wrong Legendre mode count": (
        "paper_003", {"heads.0.distortion.coeffs_x_px": [0.0, 1.0]}, located(P3, "heads.0.distortion", "(n+1)(n+2)/2"),
    ),
    "2x2 mounting matrix": (
        "paper_004", {"heads.1.mounting_matrix": [[1.0, 0.0], [0.0, 1.0]]},
        located(P4, "heads.1.mounting_matrix", "a 3x3 matrix"),
    ),
    "scaled mounting matrix": (
        "paper_004", {"heads.2.mounting_matrix": [[2.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]},
        located(P4, "heads.2.mounting_matrix", "a proper rotation matrix"),
    ),
    "reflection mounting matrix": (
        "paper_004", {"heads.0.mounting_matrix": [[1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0]]},
        located(P4, "heads.0.mounting_matrix", "proper rotation", "det +1"),
    ),
    "matrix and Euler angles": (
        "paper_004", {"heads.0.mounting_euler_deg": [0, 0, 0]}, located(P4, "heads.0.mounting_matrix", "not both"),
    ),
    "no heads": ("paper_000", {"heads": []}, located(P0, "heads", "a non-empty array of tables")),
    "head not a table": ("paper_000", {"heads": [5]}, located(P0, "heads.0", "a table", "5")),
    "inertia of strings": (
        "stress_tumble", {"motion.inertia_kgm2": ["a", "b", "c"]}, located(TUMBLE, "motion.inertia_kgm2", "3x3 tensor"),
    ),
    "ragged inertia": (
        "stress_tumble", {"motion.inertia_kgm2": [[1.0, 2.0], [3.0]]},
        located(TUMBLE, "motion.inertia_kgm2", "3 principal"),
    ),
    "unknown threshold axis": (
        "paper_000", {"availability_threshold_arcsec": {"cross_boresight": 10.0, "pitch": 5.0}},
        located(P0, "availability_threshold_arcsec.pitch", "unknown key", "cross_boresight, roll"),
    ),
    "threshold table without roll": (
        "paper_000", {"availability_threshold_arcsec": {"cross_boresight": 10.0}},
        located(P0, "availability_threshold_arcsec.roll", "a number in (0, 1e+06]", "missing"),
    ),
    "negative roll threshold": (
        "paper_001", {"availability_threshold_arcsec.roll": -1.0},
        located(P1, "availability_threshold_arcsec.roll", "(0, 1e+06]", "-1.0"),
    ),
    "NaN cross-boresight threshold": (
        "paper_001", {"availability_threshold_arcsec.cross_boresight": NAN},
        located(P1, "availability_threshold_arcsec.cross_boresight", "a number", "nan"),
    ),
    "negative total threshold": (
        "paper_000", {"availability_threshold_arcsec": -5.0},
        located(P0, "availability_threshold_arcsec", "(0, 1e+06]", "-5.0"),
    ),
    "non-physical inertia": (
        "stress_tumble", {"motion.inertia_kgm2": [1.0, 1.0, 5.0]}, located(TUMBLE, "motion", "triangle inequality"),
    ),
}


@pytest.mark.parametrize("case", INVALID, ids=list(INVALID))
def test_invalid_value_is_one_located_error(case):
    # The message reads '<file>: <dotted key>: <expected form>, got <value>' (or the model's own explanation).
    name, overrides, pattern = INVALID[case]
    with pytest.raises(ScenarioError, match=pattern):
        load(name, overrides)



@pytest.mark.parametrize(("key", "value", "field", "field_value", "bound"), [
    ("heads.0.width", 16385, "width", 16385, "[8, 16384]"),
    ("heads.0.pixel_pitch_um", 1000.5, "pixel_pitch_m", 1000.5e-6, "(0, 1000]"),  # (0, 1e-3] m
    ("heads.0.focal_length_mm", 2000.5, "focal_length_m", 2.0005, "(0, 2000]"),  # (0, 2] m
    ("heads.0.f_number", 32.5, "f_number", 32.5, "[0.5, 32]"),
    ("heads.0.psf_sigma_px", 0.05, "psf_sigma_px", 0.05, "[0.1, 20]"),
])
def test_a_scenario_refuses_a_camera_field_where_the_camera_does(key, value, field, field_value, bound):
    # One range per camera field: the scenario names its key and unit, the model its own, at the same bound.
    with pytest.raises(ScenarioError, match=re.escape(f"{key}: expected ") + r"an? \w+ in " + re.escape(bound)):
        load("paper_000", {key: value})
    args = {"focal_length_m": 0.049, "pixel_pitch_m": 20e-6, "width": 512, "height": 512, "psf_sigma_px": 1.0}
    with pytest.raises(ValueError, match=f"^{field} must be"):
        Camera.from_focal_length(**{**args, field: field_value})

@pytest.mark.parametrize(
    ("cut", "key", "expected"),
    [
        (r"^exposure_s = .*\n", "exposure_s", ("a number in (0, 0.01]", "it is missing")),
        (r"^\[\[heads\]\][\s\S]*", "heads", ("an array of tables", "it is missing")),
        (r'^kind = "constant_rate".*\n', "motion.kind", ("one of 'constant_rate', 'slew'", "it is missing")),
        (r"^focal_length_mm = .*\n", "heads.0.focal_length_mm", ("a number in (0, 2000]", "it is missing")),
        (r"^\[motion\]\n", "motion", ("a table", "it is missing")),  # its keys fall into the top level
    ],
)
def test_missing_required_field_names_the_file(tmp_path, cut, key, expected):
    # Each required field removed from a real file gives an error naming that file and the missing key.
    text = (SCENARIO_DIR / "paper_000.toml").read_text(encoding="utf-8")
    edited = re.sub(cut, "", text, count=1, flags=re.MULTILINE)
    assert edited != text
    path = tmp_path / "mission.toml"
    path.write_text(edited, encoding="utf-8")
    with pytest.raises(ScenarioError, match=located(str(path), key, *expected)):
        load(path)


def test_missing_motion_table_and_dict_source():
    # A parsed dict without [motion] is located at 'motion' and sourced as '<scenario>'.
    data = parsed("paper_000")
    del data["motion"]
    with pytest.raises(ScenarioError, match=located("<scenario>", "motion", "a table", "it is missing")):
        load(data)


def test_not_toml_and_unknown_names(tmp_path):
    # Broken TOML, undecodable bytes and an unknown scenario name are ScenarioErrors naming the culprit.
    bad = tmp_path / "broken.toml"
    bad.write_text("exposure_s = = 1\n", encoding="utf-8")
    with pytest.raises(ScenarioError, match=re.escape(f"{bad}: not valid TOML")):
        load(bad)
    bad.write_bytes(b"name = \"\xff\xfe\"\n")
    with pytest.raises(ScenarioError, match=re.escape(f"{bad}: not valid TOML")):
        load(bad)
    bad.write_text("a = " + "[" * 5000, encoding="utf-8")
    with pytest.raises(ScenarioError, match="not valid TOML"):
        load(bad)
    with pytest.raises(ScenarioError, match="neither a file nor a bundled scenario.*paper_000"):
        load("paper_999")
    with pytest.raises(ScenarioError, match="neither a file"):
        load(tmp_path / "absent.toml")


# ---------------------------------------------------------------------------------------------------------------
# Overrides.


def test_overrides_set_values_by_dotted_path():
    # Dotted paths reach scalars, vectors, list items by index and nested tables; the file itself is untouched.
    sc = load("paper_000", {"motion.rate_dps": [0, 0, 10], "heads.0.width": 256, "gyro.rate_hz": 400.0})
    np.testing.assert_allclose(sc.trajectory.body_rate(0.0), [0.0, 0.0, 10.0 * DEG])
    assert sc.heads[0].camera.width == 256 and sc.heads[0].camera.cx == 127.5
    assert sc.gyro.rate_hz == 400.0
    sc = load("paper_000", {"motion.rate_dps.2": 5.0, "heads.0.detector.adc_bits": 14})
    np.testing.assert_allclose(sc.trajectory.body_rate(0.0), np.array([1.0, 1.0, 5.0]) * DEG)
    assert sc.heads[0].detector.adc_bits == 14
    fresh = load("paper_000")
    assert fresh.heads[0].camera.width == 512 and fresh.gyro.rate_hz == 500.0


def test_overrides_leave_a_passed_dict_alone():
    # load(dict, overrides) works on a copy.
    data = parsed("paper_001")
    before = copy.deepcopy(data)
    assert load(data, {"heads.0.height": 64, "drops.probability": 0.5}).heads[0].camera.height == 64
    assert data == before


def test_overrides_create_missing_tables():
    # paper_001 has no [drops], paper_000 no [heads.stray_light] nor [motion.jitter]: overrides create them.
    assert load("paper_001", {"drops.probability": 0.25}).drops.probability == 0.25
    sc = load("paper_000", {"heads.0.stray_light.level_e_per_px_s": 100.0, "heads.0.stray_light.off_axis_deg": 40.0})
    assert sc.heads[0].stray_light.level_e_per_px_s == 100.0 and sc.heads[0].stray_light.off_axis_deg == 40.0
    sc = load("paper_000", {"motion.jitter.amplitude_arcsec": [1.0, 2.0, 3.0], "motion.jitter.frequency_hz": [5, 6, 7]})
    assert isinstance(sc.trajectory.motion, Superposed)


@pytest.mark.parametrize(
    ("name", "overrides", "pattern"),
    [
        ("paper_000", {"heads.1.width": 256}, "override 'heads.1.width': heads has 1 items, no item '1'"),
        ("paper_004", {"heads.3.name": "x"}, "heads has 3 items, no item '3'"),
        ("paper_000", {"motion.rate_dps.3": 1.0}, "motion.rate_dps has 3 items"),
        ("paper_000", {"heads.first.width": 256}, "heads has 1 items, no item 'first'"),
        ("paper_000", {"heads.-1.width": 256}, "no item '-1'"),
        ("paper_000", {"heads.\u00b2.width": 256}, "no item"),
        ("paper_000", {"exposure_s.value": 1.0}, "override 'exposure_s.value': exposure_s is not a table"),
        ("paper_000", {"motion.kind.name": "x"}, "motion.kind is not a table"),
        ("paper_000", {"heads.0.width.px": 1}, "heads.0.width is not a table"),
        ("paper_000", {"motion..kind": "slew"}, "expected a dotted key path"),
        ("paper_000", {"": 1}, "expected a dotted key path"),
        ("paper_000", {"motion.spin_dps": 1.0}, "motion.spin_dps: unknown key"),  # overrides are validated too
    ],
)
def test_bad_overrides_are_refused(name, overrides, pattern):
    # Indices past the end, non-index list keys, paths through scalars and empty parts raise a ScenarioError.
    with pytest.raises(ScenarioError, match=re.escape(bundled_file(name)) + ".*" + re.escape(pattern)):
        load(name, overrides)


def test_overrides_must_be_a_dict():
    with pytest.raises(ScenarioError, match="overrides must be a dict"):
        load("paper_000", [("exposure_s", 0.005)])


DESIGN_EXAMPLE = {
    "motion.kind": "constant_rate",
    "motion.rate_dps": [0, 0, 10],
    "motion.initial_ra_deg": 83.8,
    "motion.initial_dec_deg": -5.4,
    "motion.initial_roll_deg": 0.0,
}


def test_design_contract_example():
    # The documented override example: a 10 deg/s roll about head 0's boresight, starting on Orion.
    sc = load("paper_002", DESIGN_EXAMPLE)
    cam = sc.heads[0].camera
    np.testing.assert_allclose(sc.trajectory.body_rate(0.0), [0.0, 0.0, 10.0 * DEG])
    assert boresight_radec_deg(cam, sc.trajectory.attitude(0.0)) == pytest.approx((83.8, -5.4), abs=1e-9)
    # Head 0 looks along body +Z: rolling about it keeps the boresight on the same star.
    assert boresight_radec_deg(cam, sc.trajectory.attitude(2.0)) == pytest.approx((83.8, -5.4), abs=1e-9)
    camera0 = cam.inertial_to_camera(sc.trajectory.attitude(0.0))
    assert angle_between(camera0, pointing(83.8 * DEG, -5.4 * DEG, 0.0)) < 1e-12


@pytest.mark.parametrize(
    "mounting",
    [
        None,  # paper_004 as shipped (head 0 on body +Z, 30 deg roll)
        {"mounting_matrix": [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]},  # looking along body -X
        {"mounting_euler_deg": [25.0, -40.0, 70.0]},
    ],
)
def test_initial_pointing_is_head_0_boresight_and_roll(mounting):
    # initial_ra/dec/roll describe head 0's camera, however it is mounted on the body.
    data = parsed("paper_004")
    if mounting is not None:
        data["heads"][0].pop("mounting_matrix")
        data["heads"][0].update(mounting)
    sc = load(data)
    cam = sc.heads[0].camera
    a0 = sc.trajectory.attitude(0.0)
    assert boresight_radec_deg(cam, a0) == pytest.approx((150.0, 20.0), abs=1e-9)
    assert angle_between(cam.inertial_to_camera(a0), pointing(150.0 * DEG, 20.0 * DEG, 30.0 * DEG)) < 1e-12
    if mounting is not None:  # the body's own +Z is elsewhere: the mounting was really taken into account
        body_z = a0.inv().apply(Z)
        ra, dec = unit_to_radec(body_z)
        assert abs(math.degrees(ra) - 150.0) + abs(math.degrees(dec) - 20.0) > 1.0


# ---------------------------------------------------------------------------------------------------------------
# Round trip through to_toml.


def assert_same_mission(a: Scenario, b: Scenario) -> None:
    """Numerically the same cameras, motion, gyro and drops."""
    for key in (
        "name", "description", "seed", "duration_s", "frame_rate_hz", "exposure_s", "mag_limit", "epoch",
        "sky_mag_per_arcsec2", "lost_after_steps", "availability_threshold_arcsec",
    ):
        assert getattr(a, key) == getattr(b, key), key
    assert a.gyro == b.gyro
    assert a.drops == b.drops
    assert len(a.heads) == len(b.heads)
    for ha, hb in zip(a.heads, b.heads, strict=True):
        assert (ha.name, ha.psf_sigma_px) == (hb.name, hb.psf_sigma_px)
        assert ha.photometry == hb.photometry and ha.detector == hb.detector and ha.stray_light == hb.stray_light
        for ca, cb in ((ha.camera, hb.camera), (ha.calibrated, hb.calibrated)):
            fields = ("width", "height", "fx", "fy", "cx", "cy", "pixel_pitch_m", "aperture_m", "distortion")
            assert [getattr(ca, f) for f in fields] == [getattr(cb, f) for f in fields]
            np.testing.assert_allclose(ca.mounting.as_matrix(), cb.mounting.as_matrix(), rtol=0, atol=1e-15)
    ts = np.linspace(0.0, min(a.duration_s, 20.0), 9)
    np.testing.assert_allclose(a.trajectory.attitude(ts).as_matrix(), b.trajectory.attitude(ts).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(a.trajectory.body_rate(ts), b.trajectory.body_rate(ts), rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("name", BUNDLED)
def test_to_toml_round_trip_of_bundled(name):
    # to_toml writes TOML that loads back to the same mission.
    sc = load(name)
    assert_same_mission(sc, load(tomllib.loads(sc.to_toml())))


def test_to_toml_round_trip_with_overrides_and_awkward_values():
    # Overrides are part of the dump; strings with quotes / control characters and numpy floats stay valid TOML.
    overrides = dict(DESIGN_EXAMPLE)
    overrides.update({
        "description": 'tab\there, "quoted", back\\slash, new\nline, \x7f\x01, \u00e9\u6f22\U0001f600',
        "exposure_s": np.float64(0.05),
        "heads.0.distortion.kind": "brown_conrady",
        "heads.0.distortion.k1": -0.1,
        "heads.0.calibration.mounting_error_arcsec": [5.0, -3.0, 20.0],
        "motion.jitter.amplitude_arcsec": [1.0, 2.0, 3.0],
        "motion.jitter.frequency_hz": [5.0, 6.0, 7.0],
        "gyro.misalignment_mrad": [[0.0, 0.1, 0.0], [0.0, 0.0, -0.2], [0.3, 0.0, 0.0]],
        "drops.p_good_to_bad": 0.1,
    })
    sc = load("paper_002", overrides)
    again = load(tomllib.loads(sc.to_toml()))
    assert_same_mission(sc, again)
    assert again.description == overrides["description"]
    assert again.to_toml() == sc.to_toml()


# ---------------------------------------------------------------------------------------------------------------
# Sequences and jitter.

HEAD = {"focal_length_mm": 50.0, "pixel_pitch_um": 10.0, "width": 256, "height": 256, "mounting_euler_deg": [0, 90, 0]}
SEQUENCE = {
    "name": "sequence_test",
    "description": "hold a drift, cone, slew to Vega, then drift again",
    "duration_s": 40.0,
    "frame_rate_hz": 10.0,
    "exposure_s": 0.05,
    "motion": {
        "kind": "sequence",
        "initial_ra_deg": 10.0,
        "initial_dec_deg": 20.0,
        "initial_roll_deg": 15.0,
        "segments": [
            {"kind": "constant_rate", "duration_s": 2.0, "rate_dps": [0.5, -0.3, 1.0]},
            {"kind": "coning", "duration_s": 1.3, "half_angle_deg": 1.0, "frequency_hz": 0.3},
            {"kind": "slew", "duration_s": 25.0, "target_ra_deg": 279.23, "target_dec_deg": 38.78,
             "max_rate_dps": 10.0, "max_accel_dps2": 4.0},
            {"kind": "constant_rate", "duration_s": 5.0, "rate_dps": [0.0, 0.0, 2.0]},
        ],
    },
    "heads": [HEAD],
}
DICT = "<scenario>"  # the source named for a scenario given as a dict
JITTER = {"amplitude_arcsec": [20.0, 30.0, 10.0], "frequency_hz": [7.0, 11.0, 13.0], "phase_deg": [0.0, 0.0, 0.0]}


def assert_continuous(trajectory, t_end: float, dt: float = 1e-3) -> None:
    """No attitude jump: every step of dt turns the body by no more than the motion's rate bound allows."""
    ts = np.arange(0.0, t_end, dt)
    att = trajectory.attitude(ts)
    steps = angle_between(att[1:], att[:-1])
    assert np.all(steps <= trajectory.motion.max_rate(0.0, t_end) * dt * (1 + 1e-6) + 1e-12)


def test_sequence_loads_and_is_continuous():
    # A [[motion.segments]] script: the right segment types, continuous attitude, the slew ends on its target.
    sc = load(SEQUENCE)
    motion = sc.trajectory.motion
    assert isinstance(motion, Sequence)
    assert [type(m).__name__ for m in motion.motions] == ["ConstantRate", "Oscillation", "Slew", "ConstantRate"]
    np.testing.assert_allclose(motion.starts, [0.0, 2.0, 3.3, 28.3])
    cam = sc.heads[0].camera
    assert boresight_radec_deg(cam, sc.trajectory.attitude(0.0)) == pytest.approx((10.0, 20.0), abs=1e-9)
    np.testing.assert_allclose(sc.trajectory.body_rate(1.0), np.array([0.5, -0.3, 1.0]) * DEG)
    assert_continuous(sc.trajectory, 34.0)
    for t in motion.starts[1:]:
        assert angle_between(sc.trajectory.attitude(t - 1e-9), sc.trajectory.attitude(t)) < 1e-7
    # The slew (after a cone whose own delta(0) is not the identity) delivers head 0 onto its target.
    assert boresight_radec_deg(cam, sc.trajectory.attitude(28.3)) == pytest.approx((279.23, 38.78), abs=1e-7)


def test_jitter_is_superposed_and_bounded():
    # [motion.jitter] oscillates the attitude about the jitter-free one by at most its amplitude, continuously.
    data = copy.deepcopy(SEQUENCE)
    data["motion"]["jitter"] = JITTER
    sc, smooth = load(data), load(SEQUENCE)
    assert isinstance(sc.trajectory.motion, Superposed)
    ts = np.linspace(0.0, 34.0, 4001)
    off = angle_between(sc.trajectory.attitude(ts), smooth.trajectory.attitude(ts))
    amplitude = np.linalg.norm(JITTER["amplitude_arcsec"]) * DEG / 3600.0
    assert off.max() <= amplitude * (1 + 1e-9)
    assert off.max() > 0.5 * max(JITTER["amplitude_arcsec"]) * DEG / 3600.0
    assert_continuous(sc.trajectory, 34.0)
    # Jitter on a constant rate, from a bundled file via overrides, too.
    sc = load("paper_000", {f"motion.jitter.{k}": v for k, v in JITTER.items()})
    assert_continuous(sc.trajectory, 2.0)
    assert isinstance(sc.trajectory.motion.base, ConstantRate)


@pytest.mark.parametrize(
    ("edit", "pattern"),
    [
        (lambda m: m.pop("segments"), located(DICT, "motion.segments", "an array of tables", "missing")),
        (lambda m: m.update(segments=[]), located(DICT, "motion.segments", "a non-empty array")),
        (lambda m: m["segments"][0].update(kind="leo_nadir"), located(DICT, "motion.segments.0.kind", "one of")),
        (lambda m: m["segments"][1].update(kind="sequence"), located(DICT, "motion.segments.1.kind", "one of")),
        (lambda m: m["segments"][2].pop("duration_s"), located(DICT, "motion.segments.2.duration_s", "missing")),
        (lambda m: m["segments"][3].update(spin=1), located(DICT, "motion.segments.3.spin", "unknown key")),
        (lambda m: m.update(jitter={"amplitude_arcsec": [1, 2, 3]}), located(DICT, "motion.jitter.frequency_hz", "3")),
        (lambda m: m.update(jitter={**JITTER, "amplitude_arcsec": [-1, 2, 3]}), located(DICT, "motion.jitter")),
    ],
)
def test_invalid_sequence_or_jitter(edit, pattern):
    # Segment and jitter errors are located inside motion.segments.<i> / motion.jitter.
    data = copy.deepcopy(SEQUENCE)
    edit(data["motion"])
    with pytest.raises(ScenarioError, match=pattern):
        load(data)


# ---------------------------------------------------------------------------------------------------------------
# Fuzzing: mutated dicts and garbled files either load or raise ScenarioError, never anything else.

PARSED = {name: parsed(name) for name in BUNDLED}
SCALARS = st.one_of(
    st.sampled_from([0, -1, 2**63, -(2**63), 10**400, 1e308, -1e308, 5e-324, float("nan"), float("inf"), ""]),
    st.text(max_size=8),
    st.booleans(),
    st.integers(),
    st.floats(),  # NaN and +-inf included
)
VALUES = st.recursive(
    SCALARS, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
    max_leaves=8,
)


def nodes(tree, path=()):
    """(path, node) of every node below the root, depth first."""
    items = tree.items() if isinstance(tree, dict) else enumerate(tree) if isinstance(tree, list) else ()
    for key, child in items:
        yield path + (key,), child
        yield from nodes(child, path + (key,))


def parent_of(tree, path):
    for key in path[:-1]:
        tree = tree[key]
    return tree


@st.composite
def mutated_scenarios(draw):
    data = copy.deepcopy(PARSED[draw(st.sampled_from(BUNDLED))])
    for _ in range(draw(st.integers(1, 3))):
        everything = list(nodes(data))
        op = draw(st.sampled_from(["replace", "delete", "replace", "add", "replace", "resize"]))
        if op in ("delete", "replace") and everything:
            path, node = draw(st.sampled_from(everything))
            parent = parent_of(data, path)
            if op == "delete":
                del parent[path[-1]]
            else:
                parent[path[-1]] = draw(VALUES.filter(lambda v, n=node: type(v) is not type(n)))
        elif op == "add":
            tables = [data] + [n for _, n in everything if isinstance(n, dict)]
            draw(st.sampled_from(tables))[draw(st.text(min_size=1, max_size=10))] = draw(VALUES)
        else:
            lists = [n for _, n in everything if isinstance(n, list) and n]
            if lists:
                target = draw(st.sampled_from(lists))
                if draw(st.booleans()):
                    del target[draw(st.integers(0, len(target) - 1)):]
                else:
                    target.extend(copy.deepcopy(target[: draw(st.integers(1, len(target)))]))
    return data


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(mutated_scenarios())
def test_fuzzed_dicts_load_or_raise_scenario_error(data):
    # Any mutation of a real scenario either validates or is refused with a ScenarioError.
    try:
        sc = load(data)
    except ScenarioError as exc:
        assert str(exc).startswith("<scenario>: ")
        return
    assert isinstance(sc, Scenario)
    again = load(tomllib.loads(sc.to_toml()))  # whatever was accepted can be written out and read back
    assert (again.exposure_s, again.frame_rate_hz, len(again.heads)) == (sc.exposure_s, sc.frame_rate_hz, len(sc.heads))


@st.composite
def garbled_files(draw):
    if draw(st.booleans()):
        return draw(st.binary(max_size=300))
    text = (SCENARIO_DIR / f"{draw(st.sampled_from(BUNDLED))}.toml").read_text(encoding="utf-8")
    for _ in range(draw(st.integers(1, 4))):
        i = draw(st.integers(0, len(text)))
        j = draw(st.integers(i, min(len(text), i + 40)))
        text = text[:i] + draw(st.text(max_size=12)) + text[j:]
    return text.encode("utf-8")


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(garbled_files())
def test_fuzzed_files_load_or_raise_scenario_error(blob):
    # Random bytes and damaged scenario files: a Scenario or a ScenarioError naming the file, nothing else.
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fuzz.toml"
        path.write_bytes(blob)
        try:
            sc = load(path)
        except ScenarioError as exc:
            assert str(exc).startswith(f"{path}: ")
            return
        assert isinstance(sc, Scenario)
