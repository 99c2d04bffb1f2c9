"""Dataset specs, per-sample reproducibility, the main star on the boresight, shards and resume."""

import hashlib
import json

import numpy as np
import pytest

from starenv.datasets import DatasetError, build_dataset, load_spec, navigation_stars, read_meta, sample, shard_path
from starenv.datasets.samples import draw, render

SPEC = {
    "name": "tiny",
    "kind": "main_star",
    "scenario": "paper_002",
    "samples": 7,
    "shard_size": 3,
    "seed": 5,
    "overrides": {"heads.0.width": 64, "heads.0.height": 64, "heads.0.pixel_pitch_um": 192.0,
                  "heads.0.psf_sigma_px": 0.5},
    "randomize": {"heads.0.detector.read_noise_e": [5.0, 15.0]},
    "pointing": {"mag_limit": 5.0, "center_ra_deg": 83.8, "center_dec_deg": -5.4, "radius_deg": 15.0,
                 "roll_step_deg": 30.0},
    "rates": {"two_axis_dps": [0.0, 4.0, 8.0], "directions": 8, "roll_dps": [0.0, 6.0, -6.0]},
    "stars": {"variants": ["clean", "false", "missing"], "max_changed": 2},
}


def _digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_sample_is_a_function_of_spec_seed_and_index():
    spec = load_spec(SPEC)
    a, b = sample(spec, 4), sample(spec, 4)
    assert all(np.array_equal(a[k], b[k]) for k in a)
    assert not np.array_equal(sample(spec, 3)["image"], a["image"])
    other = load_spec({**SPEC, "seed": 6})
    assert not np.array_equal(sample(other, 4)["image"], a["image"])


@pytest.mark.parametrize("index", [0, 1, 2, 3])
def test_main_star_sits_on_the_boresight_at_mid_exposure(index):
    spec = load_spec(SPEC)
    params = draw(spec, index)
    _, frame = render(spec, params)
    truth = frame.heads[0].truth
    hip = navigation_stars(spec)[0][params["main"]]
    row = np.flatnonzero(truth.catalog_id == hip)
    assert len(row) == 1
    np.testing.assert_allclose(truth.xy_mid[row[0]], [31.5, 31.5], atol=1e-6)  # (64 - 1) / 2
    # the trail length is the rate's two-axis part times the exposure through the plate scale (small angles)
    length = np.linalg.norm(truth.xy_end[row[0]] - truth.xy_start[row[0]])
    fx = frame.heads[0].image.shape[1] / 2 / np.tan(np.radians(6.0))  # ~12 deg field on 64 px (f 58.5 mm)
    expected = np.radians(np.hypot(*params["rate_cam_dps"][:2])) * 0.092 * fx
    assert length == pytest.approx(expected, rel=0.02, abs=0.02)


def test_false_and_missing_variants_edit_the_rendered_sky():
    spec = load_spec({**SPEC, "stars": {"variants": ["false"], "max_changed": 2}})
    for i in range(3):
        params = draw(spec, i)
        truth = render(spec, params)[1].heads[0].truth
        assert (truth.catalog_id == -1).sum() == params["changed"] >= 1
    clean = load_spec({**SPEC, "stars": {"variants": ["clean"]}})
    missing = load_spec({**SPEC, "stars": {"variants": ["missing"], "max_changed": 2}})
    # same draws up to the variant: the missing-star frame has `changed` fewer stars in it
    p_clean, p_missing = draw(clean, 0), draw(missing, 0)
    n_clean = len(render(clean, p_clean)[1].heads[0].truth)
    n_missing = len(render(missing, p_missing)[1].heads[0].truth)
    assert n_clean - n_missing == p_missing["changed"]


def test_shards_are_bit_identical_and_resume_skips_complete_ones(tmp_path):
    spec = load_spec(SPEC)
    a = build_dataset(spec, tmp_path / "a", jobs=1, progress=False, log=lambda *_: None)
    b = build_dataset(spec, tmp_path / "b", jobs=2, progress=False, log=lambda *_: None)
    assert [_digest(p) for p in a] == [_digest(p) for p in b]
    assert len(a) == 3 and read_meta(a[2])["count"] == 1
    meta = read_meta(a[0])
    assert meta["spec_digest"] == spec.digest and meta["first_index"] == 0
    with np.load(a[1]) as z:
        np.testing.assert_array_equal(z["image"][0], sample(spec, 3)["image"])
        np.testing.assert_array_equal(z["index"], [3, 4, 5])
    # a killed build: one shard gone, one truncated; the rebuild redoes exactly those two
    shard_path(tmp_path / "a", 1).unlink()
    shard_path(tmp_path / "a", 2).write_bytes(b"partial")
    first = shard_path(tmp_path / "a", 0).stat().st_mtime_ns
    logs = []
    build_dataset(spec, tmp_path / "a", jobs=1, progress=False, log=logs.append)
    assert logs == [f"reusing 1 complete shard(s) in {tmp_path / 'a'}"]
    assert shard_path(tmp_path / "a", 0).stat().st_mtime_ns == first
    assert [_digest(p) for p in a] == [_digest(p) for p in b]
    info = json.loads((tmp_path / "a" / "dataset.json").read_text())
    assert load_spec(info["spec"]).digest == spec.digest


def test_another_spec_refuses_a_used_folder(tmp_path):
    build_dataset(load_spec({**SPEC, "samples": 1}), tmp_path, jobs=1, progress=False)
    with pytest.raises(DatasetError, match="holds another dataset"):
        build_dataset(load_spec({**SPEC, "samples": 2}), tmp_path, jobs=1, progress=False)


def test_centroid_kind_gives_truth_ids_and_false_stars():
    spec = load_spec({**SPEC, "kind": "centroids", "pointing": {"mode": "uniform"},
                      "stars": {"variants": ["false"], "max_changed": 1}})
    s = sample(spec, 0)
    assert s["count"] == len(s["xy"]) == len(s["catalog_id"])
    assert (s["catalog_id"] == -1).sum() <= 1 and (s["catalog_id"] > 0).sum() >= 3


def test_position_pairs_are_the_optics_and_the_calibrated_camera_on_one_direction(tmp_path):
    # paper 003's data: no image; measured = distorted + N(0, centroid_noise_px) per axis, reference = the calibrated
    # camera's projection of the same star (paper_003's distortion: up to ~2 px between the two)
    spec = load_spec({**SPEC, "kind": "position_pairs", "scenario": "paper_003", "overrides": {}, "randomize": {},
                      "pointing": {"mode": "uniform"}, "rates": {}, "stars": {}, "pairs": {"centroid_noise_px": 0.5}})
    s = sample(spec, 0)
    assert s["count"] == len(s["catalog_id"]) == len(s["measured"]) > 30 and np.all(s["catalog_id"] > 0)
    noise = s["measured"] - s["distorted"]
    assert np.all(np.abs(noise.std(axis=0) / 0.5 - 1.0) < 0.25)  # 60+ stars: the sample std within 25 %
    gap = np.abs(s["distorted"] - s["reference"]).max()
    assert 0.5 < gap < 5.0
    exact = load_spec({**spec.to_dict(), "pairs": {"centroid_noise_px": 0.0}})
    t = sample(exact, 0)
    np.testing.assert_array_equal(t["measured"], t["distorted"])
    np.testing.assert_array_equal(t["reference"], s["reference"])  # the same attitude: noise is drawn after it
    # shards: per-star rows concatenated, sample j's rows are its ``count``
    paths = build_dataset(load_spec({**spec.to_dict(), "samples": 3}), tmp_path, jobs=1, progress=False)
    with np.load(paths[0]) as z:
        assert z["count"].sum() == len(z["measured"])
        np.testing.assert_array_equal(z["measured"][z["count"][0] : z["count"][:2].sum()], sample(spec, 1)["measured"])


def test_smear_pairs_hold_each_isolated_star_and_its_sharp_image_at_mid_exposure():
    # restoration data: about each star, the smeared frame's patch and the sharp reference's (the scene over a
    # vanishing exposure at mid-exposure, DN above bias).  For a star alone in its patch the sharp patch's centre of
    # mass is the star's mid-exposure position and the smeared patch (less its border's median) holds the same light
    # up to noise and the trail's light beyond the patch.  The bounds: a patch placed a pixel (or half of one) off, or
    # cut at the wrong instant, moves the centre of mass by far more than 1e-3 px; a gain, bias or unit error puts the
    # median flux ratio well outside 0.85-1.2, which the star-to-star noise of a median does not.
    spec = load_spec({**SPEC, "kind": "smear_pairs", "overrides": {"heads.0.width": 256, "heads.0.height": 256,
                      "heads.0.pixel_pitch_um": 48.0, "heads.0.psf_sigma_px": 0.7}, "pointing": {"mode": "uniform"},
                      "stars": {}, "patches": {"size_px": 24}})
    errors, ratios = [], []
    yy, xx = np.mgrid[0:24, 0:24]
    for index in range(4):
        s = sample(spec, index)
        assert s["smeared"].dtype == np.uint16 and s["sharp"].shape == (s["count"], 24, 24)
        for smeared, sharp, origin, xy in zip(s["smeared"], s["sharp"], s["origin"], s["xy_mid"], strict=True):
            if np.sum(np.all(np.abs(s["xy_mid"] - xy) < 24, axis=1)) > 1:
                continue
            centre = np.array([(sharp * xx).sum(), (sharp * yy).sum()]) / sharp.sum()
            errors.append(np.abs(centre + origin - xy).max())
            border = np.concatenate([smeared[0], smeared[-1], smeared[:, 0], smeared[:, -1]]).astype(float)
            ratios.append((smeared - np.median(border)).sum() / sharp.sum())
    assert len(errors) >= 20 and max(errors) < 1e-3
    assert 0.85 < np.median(ratios) < 1.2


@pytest.mark.parametrize("key, value, message", [
    ("kind", "pairs", "kind: expected one of 'main_star', 'centroids', 'position_pairs', 'smear_pairs'"),
    ("patches", {"size_px": 2}, "patches.size_px: expected an integer in"),
    ("samples", 0, "samples: expected an integer in"),
    ("scenario", "nope", "scenario: expected a bundled scenario name"),
    ("rates", {"two_axis_dps": [1.0], "two_axis_range_dps": [0.0, 2.0]}, "rates.two_axis_range_dps: expected either"),
    ("stars", {"variants": ["clean", "blurred"]}, "stars.variants: expected a non-empty list"),
    ("pointing", {"radius_deg": -1.0}, "pointing.radius_deg: expected a number in"),
    ("randomize", {"heads.0.detector.read_noise_e": [3.0, 1.0]}, "randomize.heads.0.detector.read_noise_e"),
    ("overrides", {"heads.0.width": -5}, "scenario/overrides/randomize:.*heads.0.width"),
    ("colour", 1, "colour: unknown key"),
])
def test_bad_spec_names_the_field(key, value, message):
    with pytest.raises(DatasetError, match=message):
        load_spec({**SPEC, key: value})


TINY_TOML = """
name = "cli"
kind = "main_star"
scenario = "paper_002"
samples = 2
shard_size = 2
[overrides]
"heads.0.width" = 64
"heads.0.height" = 64
"heads.0.pixel_pitch_um" = 192.0
"heads.0.psf_sigma_px" = 0.5
[pointing]
mag_limit = 5.0
center_ra_deg = 83.8
center_dec_deg = -5.4
radius_deg = 15.0
"""


def test_cli_builds_a_dataset_and_names_a_bad_field(tmp_path, capsys):
    from starenv.cli import main

    good = tmp_path / "good.toml"
    good.write_text(TINY_TOML)
    assert main(["dataset", str(good), "--out", str(tmp_path / "out"), "--jobs", "1", "--quiet"]) == 0
    assert read_meta(shard_path(tmp_path / "out", 0))["count"] == 2
    bad = tmp_path / "bad.toml"
    bad.write_text(TINY_TOML.replace("radius_deg = 15.0", "radius_deg = 500.0"))
    assert main(["dataset", str(bad), "--out", str(tmp_path / "bad"), "--quiet"]) == 2
    assert "pointing.radius_deg: expected a number in [0.1, 180]" in capsys.readouterr().err


class _Killed(BaseException):
    """Stands for SIGKILL at a chosen write: nothing after it in the build runs (a BaseException, so no handler in
    the builder catches it)."""


def _files(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if not p.name.startswith(".")}


def test_a_build_killed_at_any_write_resumes_to_the_same_bytes(tmp_path, monkeypatch):
    """A build writes dataset.json, then per shard the shard and the index that records its hash: killed before any
    of those writes (and with a half-written temporary file left beside it, as a real kill leaves), the next build
    must end with the same files, byte for byte, as a build never interrupted."""
    import starenv.datasets.shards as shards

    spec = load_spec(SPEC)
    build_dataset(spec, tmp_path / "whole", jobs=1, progress=False, log=lambda *_: None)
    whole = _files(tmp_path / "whole")
    writes = 1 + 2 * spec.n_shards  # the manifest, then each shard and its index entry
    real_atomic = shards.atomic_file
    for kill_at in range(writes):
        out = tmp_path / f"killed-{kill_at}"
        count = {"n": 0}

        def atomic_file(path, *args, _out=out, _kill=kill_at, _n=count, **kwargs):
            if _n["n"] == _kill:
                (_out / f".{path.name}.partial-write.tmp").write_bytes(b"half")  # what a kill mid-write leaves
                raise _Killed
            _n["n"] += 1
            return real_atomic(path, *args, **kwargs)

        monkeypatch.setattr(shards, "atomic_file", atomic_file)
        out.mkdir()
        with pytest.raises(_Killed):
            build_dataset(spec, out, jobs=1, progress=False, log=lambda *_: None)
        monkeypatch.setattr(shards, "atomic_file", real_atomic)
        build_dataset(spec, out, jobs=1, progress=False, log=lambda *_: None)
        assert _files(out) == whole, f"killed before write {kill_at}"


def test_a_sample_replaces_the_motion_as_a_reload_does():
    """``with_motion`` (what each sample does to the once-parsed scenario) gives the mission a reload with the
    motion override gives, and refuses what the loader refuses (a trail over its bound)."""
    from starenv import scenario as scenario_mod

    base = scenario_mod.load("paper_002")
    motion = {"kind": "constant_rate", "rate_dps": [1.5, -2.0, 6.0], "initial_ra_deg": 10.0, "initial_dec_deg": -30.0,
              "initial_roll_deg": 45.0}
    fast, reloaded = scenario_mod.with_motion(base, motion), scenario_mod.load("paper_002", {"motion": motion})
    for t in (0.0, 0.046, 1.0):
        assert np.array_equal(fast.trajectory.attitude(t).as_quat(), reloaded.trajectory.attitude(t).as_quat())
    assert fast.to_toml() == reloaded.to_toml()
    with pytest.raises(scenario_mod.ScenarioError, match="star trails of at most"):
        scenario_mod.with_motion(base, {**motion, "rate_dps": [900.0, 0.0, 0.0]})
