"""A scenario from your sensor: ``starenv scenarios --show`` prints a bundled file as it is, ``starenv new`` writes a
documented scenario from datasheet values whose derived figures match their closed forms (checked against
independent computations) and the simulator itself, and that the env runs."""

from __future__ import annotations

import math
import re
import shlex
import tomllib
from pathlib import Path

import numpy as np
import pytest
from scipy import integrate, optimize

from starenv import cli
from starenv.env import StarSensorEnv
from starenv.scenario import HIP_COUNT_AT_MAG, SCENARIO_DIR, bundled_names, load
from starenv.sensor_sheet import (
    SensorSheet,
    derived,
    limiting_electrons,
    rectangle_solid_angle_sr,
    scenario_text,
    stars_brighter,
)

ROOT = Path(__file__).resolve().parents[1]
ARCSEC_PER_RAD = 180.0 / math.pi * 3600.0
# a 1024 x 768 head of 5.5 um behind f = 25 mm, D = 20 mm, 50 ms at 10 Hz, with its noise figures
SHEET = dict(focal_length_mm=25.0, pixel_pitch_um=5.5, width=1024, height=768, aperture_mm=20.0, exposure_ms=50.0,
             frame_rate_hz=10.0, read_noise_e=3.0, dark_current_e_per_s=10.0, full_well_e=10000.0,
             gain_e_per_dn=1.5, quantum_efficiency=0.7, transmission=0.85, psf_sigma_px=1.2, snr=6.0)
NEW_ARGS = ["new", "--focal-mm", "25", "--pixel-um", "5.5", "--resolution", "1024", "768", "--aperture-mm", "20",
            "--exposure-ms", "50", "--rate-hz", "10", "--read-noise-e", "3", "--dark-current-e-s", "10",
            "--full-well-e", "10000", "--gain-e-dn", "1.5", "--qe", "0.7", "--transmission", "0.85",
            "--psf-sigma-px", "1.2", "--snr", "6"]


def test_show_prints_a_bundled_scenario_file_exactly_and_the_list_is_unchanged(capsys):
    for name in ("paper_000", "stress_tumble"):
        assert cli.main(["scenarios", "--show", name]) == 0
        assert capsys.readouterr().out == (SCENARIO_DIR / f"{name}.toml").read_text(encoding="utf-8")
    assert cli.main(["scenarios"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in lines] == bundled_names()
    assert cli.main(["scenarios", "--show", "paper_9"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "'paper_9': not a bundled scenario (" in err and "paper_000" in err


def test_the_derived_figures_match_their_closed_forms():
    sheet = SensorSheet(**SHEET)
    got = {k: v for k, (v, _, _) in derived(sheet).items()}
    f_m, p_m, d_m, t = 25e-3, 5.5e-6, 20e-3, 0.05
    assert got["focal_length_px"] == pytest.approx(f_m / p_m, rel=1e-12)
    assert got["f_number"] == pytest.approx(1.25, rel=1e-12)
    assert got["fov_width_deg"] == pytest.approx(math.degrees(2 * math.atan(1024 * p_m / 2 / f_m)), rel=1e-12)
    assert got["fov_height_deg"] == pytest.approx(math.degrees(2 * math.atan(768 * p_m / 2 / f_m)), rel=1e-12)
    assert got["fov_diagonal_deg"] == pytest.approx(math.degrees(2 * math.atan(1280 * p_m / 2 / f_m)), rel=1e-12)
    assert got["ifov_arcsec_per_px"] == pytest.approx(p_m / f_m * ARCSEC_PER_RAD, rel=1e-12)
    assert got["ifov_urad_per_px"] == pytest.approx(p_m / f_m * 1e6, rel=1e-12)
    assert got["plate_scale_arcsec_per_mm"] == pytest.approx(1e-3 / f_m * ARCSEC_PER_RAD, rel=1e-12)
    assert got["airy_diameter_px"] == pytest.approx(2.44 * 550e-9 * 1.25 / p_m, rel=1e-12)
    photons = 1.9e10 * math.pi * (d_m / 2) ** 2  # the zero point over the pupil's area
    assert got["photons_per_s_mag0"] == pytest.approx(photons, rel=1e-12)
    assert got["electrons_per_s_mag0"] == pytest.approx(photons * 0.85 * 0.7, rel=1e-12)
    assert got["electrons_mag0_per_exposure"] == pytest.approx(photons * 0.85 * 0.7 * t, rel=1e-12)
    sky = photons * 0.85 * 0.7 * 10 ** (-0.4 * 22.0) * (p_m / f_m * ARCSEC_PER_RAD) ** 2
    assert got["sky_e_per_px_s"] == pytest.approx(sky, rel=1e-12)
    assert got["noise_e_per_px"] == pytest.approx(math.sqrt(9.0 + (10.0 + sky) * t), rel=1e-12)
    assert got["smear_px_per_dps"] == pytest.approx(f_m / p_m * t * math.pi / 180, rel=1e-12)
    assert got["frame_period_ms"] == pytest.approx(100.0, rel=1e-12)
    assert got["adc_full_scale_e"] == pytest.approx((4095 - 100) * 1.5, rel=1e-12)


def test_the_limiting_magnitude_solves_the_snr_equation():
    sheet = SensorSheet(**SHEET)
    got = {k: v for k, (v, _, _) in derived(sheet).items()}
    area, variance = 4 * math.pi * 1.2**2, got["noise_e_per_px"] ** 2
    # the signal at SNR 6 found by a root finder on S / sqrt(S + A v) - 6, independent of the quadratic's root
    signal = optimize.brentq(lambda s: s / math.sqrt(s + area * variance) - 6.0, 1e-6, 1e9, xtol=1e-12)
    assert limiting_electrons(6.0, variance, area) == pytest.approx(signal, rel=1e-9)
    assert got["limiting_magnitude"] == pytest.approx(-2.5 * math.log10(signal / got["electrons_mag0_per_exposure"]),
                                                      abs=1e-9)
    # a fainter star's SNR is lower: the limit is where it crosses 6 (one magnitude = a factor 10^0.4)
    fainter = signal * 10 ** -0.4
    assert fainter / math.sqrt(fainter + area * variance) < 6.0


def test_the_saturation_magnitude_uses_the_share_of_a_centred_spot_in_its_pixel():
    sheet = SensorSheet(**SHEET)
    got = {k: v for k, (v, _, _) in derived(sheet).items()}
    sigma = 1.2
    share, _ = integrate.dblquad(lambda y, x: math.exp(-(x * x + y * y) / (2 * sigma**2)) / (2 * math.pi * sigma**2),
                                 -0.5, 0.5, -0.5, 0.5, epsabs=1e-12)
    expected = -2.5 * math.log10(10000.0 / (share * got["electrons_mag0_per_exposure"]))
    assert got["saturation_magnitude"] == pytest.approx(expected, abs=1e-6)


def test_stars_in_the_field_from_the_catalogue_counts_and_the_field_solid_angle():
    # the solid angle of a rectangular field, integrated over its tangent plane: dA / (1 + x^2 + y^2)^(3/2)
    a, b = math.radians(20.0), math.radians(12.0)
    ta, tb = math.tan(a / 2), math.tan(b / 2)
    omega, _ = integrate.dblquad(lambda y, x: (1 + x * x + y * y) ** -1.5, -ta, ta, -tb, tb, epsabs=1e-12)
    assert rectangle_solid_angle_sr(a, b) == pytest.approx(omega, rel=1e-9)
    assert rectangle_solid_angle_sr(math.pi, math.pi) == pytest.approx(2 * math.pi, rel=1e-12)  # a hemisphere
    for m in range(-1, 15):  # whole magnitudes give the catalogue's counts; between them, geometric steps
        assert stars_brighter(float(m)) == pytest.approx(HIP_COUNT_AT_MAG[m + 2], rel=1e-12)
    assert stars_brighter(7.5) == pytest.approx(math.sqrt(HIP_COUNT_AT_MAG[9] * HIP_COUNT_AT_MAG[10]), rel=1e-12)
    sheet = SensorSheet(**SHEET)
    got = {k: v for k, (v, _, _) in derived(sheet).items()}
    share = rectangle_solid_angle_sr(math.radians(got["fov_width_deg"]), math.radians(got["fov_height_deg"])) / (
        4 * math.pi)
    assert got["stars_in_field"] == pytest.approx(stars_brighter(got["limiting_magnitude"]) * share, rel=1e-12)


def test_a_field_of_view_gives_the_focal_length_that_reproduces_it():
    sheet = SensorSheet(**{**SHEET, "focal_length_mm": None, "fov_deg": 17.5})
    got = {k: v for k, (v, _, _) in derived(sheet).items()}
    assert got["fov_width_deg"] == pytest.approx(17.5, rel=1e-12)
    assert got["focal_length_mm"] == pytest.approx(1024 * 5.5e-3 / 2 / math.tan(math.radians(17.5) / 2), rel=1e-12)
    with pytest.raises(ValueError, match="one of them"):
        SensorSheet(**{**SHEET, "fov_deg": 17.5})
    with pytest.raises(ValueError, match="--exposure-ms 200: expected at most the frame period 100 ms"):
        SensorSheet(**{**SHEET, "exposure_ms": 200.0})


def test_new_writes_a_documented_scenario_the_loader_accepts_with_every_figure_in_a_comment(tmp_path, capsys):
    out = tmp_path / "mine.toml"
    assert cli.main([*NEW_ARGS, "--out", str(out)]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    text = out.read_text(encoding="utf-8")
    figures = derived(SensorSheet(**SHEET))
    for key, (value, _, _) in figures.items():  # every derived figure, with its value, in a comment
        found = re.search(rf"^#\s+{key}\s+(\S+)", text, re.M)
        assert found and float(found.group(1)) == pytest.approx(value, rel=1e-4), key
    data = tomllib.loads(text)
    head = data["heads"][0]
    assert (head["focal_length_mm"], head["pixel_pitch_um"], head["width"], head["height"]) == (25.0, 5.5, 1024, 768)
    assert data["heads"][0]["detector"]["read_noise_e"] == 3.0 and data["exposure_s"] == 0.05
    assert "# datasheet" in text.split("quantum_efficiency", 1)[1].splitlines()[0]
    sc = load(out)  # the loader's camera and photometry are the ones the comments describe
    value = {k: v for k, (v, _, _) in figures.items()}
    cam, photometry = sc.heads[0].camera, sc.heads[0].photometry
    assert cam.fx == pytest.approx(value["focal_length_px"], rel=1e-6)
    assert photometry.electrons_per_s_mag0 == pytest.approx(value["electrons_per_s_mag0"], rel=1e-5)
    assert cli.main([*NEW_ARGS, "--out", str(out)]) == 2  # an existing file is replaced only with --force
    assert "exists; --force replaces it" in capsys.readouterr().err
    assert cli.main([*NEW_ARGS, "--out", str(out), "--force", "--name", "other"]) == 0
    assert load(out).name == "other"


def test_the_env_runs_the_new_scenario_and_renders_the_stated_flux():
    text = scenario_text(SensorSheet(**{**SHEET, "duration_s": 0.3}))
    env = StarSensorEnv(tomllib.loads(text))
    obs, info = env.reset(seed=0)
    e0_t = derived(SensorSheet(**SHEET))["electrons_mag0_per_exposure"][0]
    stars = info["truth"]["stars"][0]
    inside = [(m, e) for m, e, xy in zip(stars["magnitude"], stars["electrons"], stars["xy_mid"], strict=True)
              if 10 <= xy[0] <= 1013 and 10 <= xy[1] <= 757]
    assert len(inside) >= 5
    for magnitude, electrons in inside:  # a star well inside the frame delivers e0 t 10^(-0.4 m) (f-number rounding)
        assert electrons == pytest.approx(e0_t * 10 ** (-0.4 * magnitude), rel=1e-4)
    obs, reward, terminated, truncated, info = env.step({"attitude": info["truth"]["attitude"], "attitude_valid": 1})
    assert obs["frames"].shape == (1, 768, 1024) and np.isfinite(reward)


def test_the_readme_commands_write_and_run_a_scenario(tmp_path, capsys, monkeypatch):
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    section = readme.split("## Your own sensor", 1)[1].split("```bash", 1)[1].split("```", 1)[0]
    commands = [shlex.split(c) for c in section.replace("\\\n", " ").splitlines() if c.strip()]
    commands = [c[: c.index("#")] if "#" in c else c for c in commands]
    monkeypatch.chdir(tmp_path)
    assert [c[:2] for c in commands] == [["starenv", "scenarios"], ["starenv", "new"], ["starenv", "run"]]
    shown, written, run = commands
    assert cli.main(shown[1:shown.index(">")]) == 0
    assert capsys.readouterr().out == (SCENARIO_DIR / "paper_000.toml").read_text(encoding="utf-8")
    assert cli.main(written[1:]) == 0
    sc = load(tmp_path / written[written.index("--out") + 1])
    assert sc.heads[0].camera.width == 1024 and sc.exposure_s == 0.05
    assert cli.main([*run[1:run.index("--steps")], "--steps", "2", "--quiet"]) == 0


def test_new_refuses_incomplete_or_inconsistent_datasheets(capsys):
    assert cli.main(["new", "--fov", "20", "--pixel-um", "5.5", "--resolution", "512", "512"]) == 2
    assert "new: give --aperture-mm, --exposure-ms, --rate-hz" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # a field of view and a focal length are one or the other
        cli.main(["new", "--fov", "20", "--focal-mm", "25"])
    capsys.readouterr()
    args = [a if a != "20" else "100" for a in NEW_ARGS]  # a 100 mm aperture behind 25 mm: f/0.25
    assert cli.main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "heads.0.f_number: expected a number in [0.5, 32], got 0.25" in err
