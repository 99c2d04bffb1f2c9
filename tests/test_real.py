"""Real frames in: reading image files (every refusal one line naming the file), the spot size measured on frames
rendered with known spots, and the committed real frames solved lost in space and checked against cedar-solve's
solutions (``tests/data/real/reference.json``, made by ``benchmarks/real_frames.py --reference``) and against the
catalogue through the solved WCS."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from starenv import scenario
from starenv.agents.blocks import background
from starenv.agents.detect import CentroidDetector
from starenv.agents.detect.spot import measure_spot_sigma
from starenv.cli import main
from starenv.real import FrameFileError, FrameSolver, camera_from_fov, read_frame, solve_frame
from starenv.real.solve import FOV_TOLERANCE, scaled_camera
from starenv.scenario import ScenarioError, load_camera
from starenv.sim.conventions import DEG, pointing
from starenv.sim.sensor import StarSensor

DATA = Path(__file__).parent / "data" / "real"
FRAMES = sorted(DATA.glob("2019-*"))
REFERENCE = json.loads((DATA / "reference.json").read_text())["frames"]
EPOCH = 2019.58  # the frames were taken on 2019-07-29
ARCSEC = DEG / 3600.0


# --- reading --------------------------------------------------------------------------------------------------------

def test_the_committed_frames_read_as_16_bit_grey():
    for path in FRAMES:
        image = read_frame(path)
        assert image.dtype == np.uint16 and image.shape == (768, 1024)
    tiff, png = read_frame(FRAMES[0]), read_frame(FRAMES[1])
    assert FRAMES[1].suffix == ".png" and tiff.shape == png.shape


def test_8_bit_png_grey_as_colour_and_fits_are_read(tmp_path):
    grey = (np.arange(64 * 48) % 251).astype(np.uint8).reshape(48, 64)
    cv2.imwrite(str(tmp_path / "g.png"), grey)
    cv2.imwrite(str(tmp_path / "rgb.png"), np.dstack([grey] * 3))
    assert np.array_equal(read_frame(tmp_path / "g.png"), grey)
    assert np.array_equal(read_frame(tmp_path / "rgb.png"), grey)
    fits = pytest.importorskip("astropy.io.fits")
    counts = (np.arange(64 * 48) * 37 % 65535).astype(np.uint16).reshape(48, 64)
    fits.PrimaryHDU(counts).writeto(tmp_path / "f.fits")
    from_fits = read_frame(tmp_path / "f.fits")
    assert np.array_equal(from_fits, counts) and from_fits.dtype.isnative


def _huge_png(path: Path) -> None:
    """A PNG whose header declares 100 000 x 100 000 px (the pixels are never reached)."""
    cv2.imwrite(str(path), np.zeros((4, 4), np.uint8))
    data = bytearray(path.read_bytes())
    data[16:24] = (100_000).to_bytes(4, "big") * 2
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("case, words", [
    ("missing", "cannot be read"), ("empty", "is empty"), ("text", "not a valid PNG"), ("float", "float32 pixels"),
    ("colour", "colour image"), ("huge", "more than"), ("cube", "image cube"), ("truncated", "cannot be decoded"),
])
def test_bad_files_are_refused_in_one_line_naming_the_file(tmp_path, case, words, capsys):
    path = tmp_path / {"float": "f.tiff", "cube": "c.fits"}.get(case, f"{case}.png")
    if case == "empty":
        path.write_bytes(b"")
    elif case == "text":
        path.write_text("not an image\n")
    elif case == "float":
        cv2.imwrite(str(path), np.ones((8, 8), np.float32))
    elif case == "colour":
        cv2.imwrite(str(path), np.dstack([np.zeros((8, 8), np.uint8), np.ones((8, 8), np.uint8), np.zeros((8, 8),
                                                                                                        np.uint8)]))
    elif case == "huge":
        _huge_png(path)
    elif case == "cube":
        fits = pytest.importorskip("astropy.io.fits")
        fits.PrimaryHDU(np.zeros((3, 8, 8), np.uint16)).writeto(path)
    elif case == "truncated":
        cv2.imwrite(str(path), (np.arange(4096) % 256).astype(np.uint8).reshape(64, 64))
        path.write_bytes(path.read_bytes()[:60])
    with pytest.raises(FrameFileError) as caught:
        read_frame(path)
    message = str(caught.value)
    assert message.startswith(str(path)) and words in message and "\n" not in message
    assert main(["solve", str(path), "--fov", "10"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and words in err[0]


# --- the spot size measured ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("sigma_px", [0.5, 1.0, 1.5, 2.0, 2.5])
def test_the_spot_is_measured_on_rendered_frames_and_the_stars_are_kept(sigma_px):
    """Rendered still frames (paper 002's head) with a known Gaussian spot: the measurement is within
    ``TOLERANCE`` of it, and the detector handed the measured sigma keeps as many true stars as with the true one.
    TOLERANCE: each fitted star peaks at least PEAK_SIGMA = 20 noise sigmas above the background, so one fit's
    sigma is good to about 1/20 = 5 %; the median of several fits is better still."""
    tolerance = 0.05
    sc = scenario.load("paper_002", {"motion.rate_dps": [0, 0, 0], "heads.0.psf_sigma_px": sigma_px})
    sensor = StarSensor(sc)
    sensor.reset(0)
    head = sensor.next_frame().heads[0]
    spot = measure_spot_sigma(head.image)
    assert spot is not None and abs(spot.sigma_px / sigma_px - 1.0) < tolerance
    truth = head.truth.xy_centroid[head.truth.detectable]
    camera = sc.heads[0].calibrated

    def kept(sigma):
        stars = CentroidDetector().detect(head.image, dataclasses.replace(camera, psf_sigma_px=sigma))
        return int(np.sum(cKDTree(stars.xy).query(truth)[0] < 1.5)) if len(stars) else 0

    with_truth = kept(sigma_px)
    assert with_truth > 0.5 * len(truth) and kept(spot.sigma_px) >= with_truth
    if sigma_px == 0.5:  # the failure the measurement removes: a 1 px default rejects sharp stars as hot pixels
        assert kept(1.0) < 0.5 * with_truth


def test_a_frame_of_hot_pixels_alone_gives_no_spot():
    """Single bright pixels on noise have no light beside their peak: nothing to measure, no guess."""
    rng = np.random.default_rng(0)
    image = rng.normal(100.0, 3.0, (256, 256))
    image[rng.integers(0, 256, 40), rng.integers(0, 256, 40)] = 3000.0
    assert measure_spot_sigma(np.rint(image).astype(np.uint16)) is None


# --- the committed real frames solved ---------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def real_solutions():
    camera_file = load_camera(DATA / "tetra3_camera.toml")
    assert not camera_file.spot_calibrated  # the file leaves the spot to be measured
    solver = FrameSolver(camera_file.camera, spot_calibrated=False, epoch=EPOCH)
    return camera_file.camera, solver, {p.name: solver.solve(read_frame(p), file=p.name) for p in FRAMES}


def test_real_frames_are_solved_and_agree_with_cedar_solve(real_solutions):
    """Every committed frame solves with no prior.  Bounds: the residual rms is below half a pixel (an identified
    star further off would be a wrong id or a wrong camera).  Against cedar-solve's solution of the same frame: with
    centroids good to ``CENTROID_PX`` and at least ``STARS`` stars, each solver's boresight is good to
    CENTROID_PX / sqrt(STARS) px and its roll to that over the stars' typical distance from the centre
    (``RADIUS_PX``); the two differ by sqrt(2) of that, and the bounds are 3 times it."""
    centroid_px, stars, radius_px = 0.25, 14, 300.0
    camera, _, solutions = real_solutions
    across_bound = 3.0 * math.sqrt(2.0) * centroid_px / math.sqrt(stars) / camera.fx / ARCSEC
    roll_bound = across_bound * camera.fx / radius_px
    for name, solution in solutions.items():
        assert solution.solved and solution.stars_identified >= stars and solution.residual_rms_px < 0.5, name
        ref = REFERENCE[name]
        theirs = pointing(ref["RA"] * DEG, ref["Dec"] * DEG, ref["Roll"] * DEG)
        error = (solution.attitude * theirs.inv()).as_rotvec()  # about the camera axes (ICRS -> camera attitudes)
        assert math.hypot(error[0], error[1]) / ARCSEC < across_bound, name
        assert abs(error[2]) / ARCSEC < roll_bound, name
        assert abs(math.remainder(solution.roll_deg - ref["Roll"], 360.0)) * 3600 < roll_bound + across_bound


def test_real_frames_need_the_measured_spot(real_solutions):
    """The spot measured on the real frames is sharper than the 1 px default, and with that default the detector
    throws stars away: fewer identified, and the first frame (a sparse field) not solved at all."""
    camera, _, solutions = real_solutions
    default = FrameSolver(camera, spot_calibrated=True, epoch=EPOCH)
    for path in FRAMES:
        measured = solutions[path.name]
        assert measured.spot_measured and 0.3 < measured.spot_sigma_px < camera.psf_sigma_px
        with_default = default.solve(read_frame(path))
        assert with_default.stars_identified < measured.stars_identified
    assert not default.solve(read_frame(FRAMES[0])).solved


def test_a_network_trained_only_on_the_twins_frames_identifies_real_frames_and_never_wrongly():
    """Sim to real: paper 002's network trained only on frames of the camera's twin (the shipped tetra3_twin_sky
    weights), with the local background (the real sky is not flat) and its centre stars drawn from the 20 brightest
    detections, as the pipeline file the docs give to `starenv solve` sets it up, beside the lost-in-space identifier
    in the same solver and camera (checked against cedar-solve above).  Every label the network gives must be the
    one the lost-in-space solution gives the same detection, and the two attitudes must agree within 30 arcsec
    (0.75 px; a wrong main star or roll is degrees off); at least one of the three frames must be solved (a network
    that reads the real frames wrongly solves none: with the frame's median as background, none is)."""
    from starenv.agents.pipeline import Pipeline

    docs = Path(__file__).parent.parent / "docs" / "real_frames"
    camera = load_camera(docs / "tetra3_twin.toml").camera
    pipeline = Pipeline.from_spec(scenario.load_pipeline(docs / "tetra3_twin_network.toml"))
    identifier = pipeline.agents["identifier"]
    assert identifier.weights.name == "tetra3_twin_sky" and pipeline.agents["predictor"] is None
    assert (identifier.background, identifier.brightest, identifier.centre_stars, identifier.top_k) == \
        ("local", 20, 15, 10)
    network = FrameSolver(camera, pipeline, epoch=EPOCH, fov_tolerance=0.0)
    classical = FrameSolver(camera, epoch=EPOCH, fov_tolerance=0.0)
    solved = 0
    for path in FRAMES:
        image = read_frame(path)
        got, ref = network.solve(image), classical.solve(image)
        assert ref.solved, path.name
        if not got.solved:
            continue
        solved += 1
        labels = {(star.x_px, star.y_px): star.hip for star in ref.stars}
        assert all(labels.get((star.x_px, star.y_px), star.hip) == star.hip for star in got.stars), path.name
        assert (got.attitude * ref.attitude.inv()).magnitude() / ARCSEC < 30.0, path.name
    assert solved >= 1


def test_the_solved_wcs_maps_the_identified_stars_onto_the_catalogue(tmp_path, real_solutions):
    """``starenv solve --wcs-fits``: astropy's WCS of the written file takes each identified star's pixel to the sky
    within its own residual (the camera has no distortion, so the TAN WCS is the camera model; a TAN pixel spans at
    most 1/fx rad), and the JSON holds every field of the solution."""
    wcs_mod = pytest.importorskip("astropy.wcs")
    fits = pytest.importorskip("astropy.io.fits")
    camera, solver, _ = real_solutions
    out = tmp_path / "solved.json"
    assert main(["solve", str(FRAMES[0]), "--camera", str(DATA / "tetra3_camera.toml"), "--epoch", str(EPOCH),
                 "--json", str(out), "--wcs-fits", str(tmp_path / "wcs")]) == 0
    (record,) = json.loads(out.read_text())
    for key in ("file", "solved", "attitude_xyzw", "ra_deg", "dec_deg", "roll_deg", "fov_deg", "stars_detected",
                "stars_identified", "residual_rms_px", "time_ms", "stars", "fov_searched", "fov_fitted_deg",
                "fov_fitted_sigma_deg"):
        assert key in record
    assert set(record["stars"][0]) == {"x_px", "y_px", "hip", "residual_px"}
    with fits.open(tmp_path / "wcs" / (FRAMES[0].stem + ".fits")) as hdus:
        wcs = wcs_mod.WCS(hdus[0].header)
        assert np.array_equal(hdus[0].data, read_frame(FRAMES[0]))
    stars = record["stars"]
    xy = np.array([[s["x_px"], s["y_px"]] for s in stars])
    ra, dec = wcs.all_pix2world(xy[:, 0], xy[:, 1], 0)
    sky = np.column_stack([np.cos(np.radians(dec)) * np.cos(np.radians(ra)),
                           np.cos(np.radians(dec)) * np.sin(np.radians(ra)), np.sin(np.radians(dec))])
    rows = np.searchsorted(solver.catalog.hip, [s["hip"] for s in stars])
    separation = np.arccos(np.clip(np.sum(sky * solver.catalog.unit[rows], axis=1), -1.0, 1.0))
    residual = np.array([s["residual_px"] for s in stars])
    assert np.all(separation <= residual / camera.fx + 1e-7)


# --- the field searched ----------------------------------------------------------------------------------------------

def _across_and_roll_arcsec(attitude, ref) -> tuple[float, float]:
    """Angles (arcsec) across the boresight and about it of the rotation from cedar-solve's solution to ``attitude``."""
    error = (attitude * pointing(ref["RA"] * DEG, ref["Dec"] * DEG, ref["Roll"] * DEG).inv()).as_rotvec()
    return math.hypot(error[0], error[1]) / ARCSEC, abs(error[2]) / ARCSEC


@pytest.mark.parametrize("scale", [1.05, 0.95])
def test_a_field_5_percent_off_is_found_and_fitted(real_solutions, scale):
    """The committed frames solved with the camera's focal length 5 % off (its field about 5 % off), far beyond what
    the identifier takes (its edges and match radius hold the scale to ``scale_tolerance``, N_SIGMA sqrt 2 centroid
    noise over the shorter side: 0.28 %): the search over +- ``FOV_TOLERANCE`` finds the field, and the
    solution is the one of the camera as calibrated: the field fitted to the stars within 3 of its 1 sigma of the
    field fitted there (the same stars: only the search's start differs), within ``scale_tolerance`` of the camera
    file's field (which solves these frames with no search, so the identifier took it within that tolerance), and
    the attitude within the bounds of the cedar-solve comparison above."""
    camera, exact, solutions = real_solutions
    off = FrameSolver(scaled_camera(camera, scale), spot_calibrated=False, epoch=EPOCH)
    assert off.scale_tolerance == pytest.approx(3.0 * math.sqrt(2.0) * 0.5 / camera.height)
    calibrated_fov = math.degrees(camera.fov[0])
    for path in FRAMES:
        given = solutions[path.name]
        solution = off.solve(read_frame(path), file=path.name)
        assert not given.fov_searched and abs(given.fov_fitted_deg / calibrated_fov - 1.0) < exact.scale_tolerance
        assert solution.solved and solution.fov_searched and solution.stars_identified >= given.stars_identified
        assert abs(solution.fov_fitted_deg - given.fov_fitted_deg) < 3.0 * given.fov_fitted_sigma_deg
        assert abs(solution.fov_deg / calibrated_fov - 1.0) < off.scale_tolerance
        across, roll = _across_and_roll_arcsec(solution.attitude, REFERENCE[path.name])
        across_bound = 3.0 * math.sqrt(2.0) * 0.25 / math.sqrt(14) / camera.fx / ARCSEC
        assert across < across_bound and roll < across_bound * camera.fx / 300.0


def test_no_search_without_a_tolerance_and_the_grid_steps_by_twice_the_tolerance(real_solutions):
    """``fov_tolerance=0``: a camera 5 % off is not searched (the frame stays unsolved).  The grid: factors 1 +- k
    step, step twice the scale tolerance (a true scale anywhere in the range is within the tolerance of one), nearest
    to 1 first, none beyond the range."""
    camera, exact, _ = real_solutions
    fixed = FrameSolver(scaled_camera(camera, 1.05), spot_calibrated=False, epoch=EPOCH, fov_tolerance=0.0)
    assert fixed.scales == [] and not fixed.solve(read_frame(FRAMES[0])).solved
    scales = np.array(exact.scales)
    step = 2.0 * exact.scale_tolerance
    assert np.all(np.abs(scales - 1.0) <= FOV_TOLERANCE) and np.all(np.diff(np.abs(scales - 1.0)) > -1e-12)
    grid = np.sort(np.r_[1.0, scales])
    assert np.allclose(np.diff(grid), step) and grid[-1] > 1.0 + FOV_TOLERANCE - step


# --- a background cut at 0 DN ---------------------------------------------------------------------------------------

def test_a_simulated_frame_with_its_background_cut_at_zero_solves(monkeypatch):
    """paper_002's head, still, less its background level (the noise-free frame's median: bias, sky and dark) and cut
    at 0 DN, as a camera that subtracts its black level on board: half the pixels read 0.  The detector's noise then
    comes from the Gaussian behind the cut (per tile of 1024 pixels, good to about 5 %: a quarter of a sigma at a
    5 sigma threshold), so it finds as many stars as on the uncut frame (within 10 %), the frame solves lost in space
    and the attitude is within 3 pixels' worth of the truth (a fraction of a pixel per star, averaged over tens of
    stars).  With the sigma-clipped statistics alone (the censored path off), the noise reads a third too low and the
    detections more than triple."""
    sc = scenario.load("paper_002", {"motion.rate_dps": [0, 0, 0]})
    sensor = StarSensor(sc)
    sensor.reset(0)
    frame = sensor.next_frame()
    head = frame.heads[0]
    level = float(np.median(sensor.still_frame(0, head.truth)))
    cut = np.maximum(head.image.astype(np.float64) - round(level), 0.0).astype(np.uint16)
    assert np.mean(cut == 0) > 0.4
    camera = sc.heads[0].calibrated
    uncut_stars = CentroidDetector().detect(head.image, camera)
    cut_stars = CentroidDetector().detect(cut, camera)
    assert abs(len(cut_stars) / len(uncut_stars) - 1.0) < 0.1
    solution = FrameSolver(camera, spot_calibrated=True, epoch=sc.epoch, fov_tolerance=0.0).solve(cut)
    truth = camera.inertial_to_camera(frame.attitude)
    assert solution.solved and solution.stars_identified >= 10
    assert (solution.attitude * truth.inv()).magnitude() < 3.0 / camera.fx
    monkeypatch.setattr(background, "CLIPPED_FRACTION", 2.0)  # never: the sigma-clipped statistics alone
    assert len(CentroidDetector().detect(cut, camera)) > 3 * len(uncut_stars)


# --- the camera -------------------------------------------------------------------------------------------------------

def test_camera_from_fov_spans_the_field_across_the_columns():
    camera = camera_from_fov(11.4, (768, 1024))
    assert camera.width == 1024 and camera.height == 768
    assert math.isclose(math.degrees(camera.fov[0]), 11.4, rel_tol=1e-12)
    assert (camera.cx, camera.cy) == (511.5, 383.5)


def test_a_camera_file_is_validated_as_a_scenario_head(tmp_path):
    path = tmp_path / "cam.toml"
    path.write_text("[camera]\nfocal_length_mm = 35\npixel_pitch_um = 6.9\nwidth = 1024\nheight = 768\n"
                    "psf_sigma_px = 0.6\nlens = 'f/1.9'\n")
    with pytest.raises(ScenarioError, match=r"cam.toml: camera.lens: unknown key"):
        load_camera(path)
    path.write_text("[camera]\nfocal_length_mm = 35\npixel_pitch_um = 6.9\nwidth = 1024\nheight = 768\n"
                    "psf_sigma_px = 0.6\n")
    camera_file = load_camera(path)
    assert camera_file.spot_calibrated and camera_file.camera.psf_sigma_px == 0.6


def test_solve_frame_refuses_a_frame_of_another_size():
    with pytest.raises(ValueError, match="does not match the camera"):
        solve_frame(np.zeros((100, 100), np.uint16), camera_from_fov(10.0, (200, 200)))


def test_solve_takes_a_pipeline_file_and_refuses_a_frame_of_another_camera(tmp_path, capsys):
    """``--pipeline``: the file's [pipeline] table reaches the agents (the detector's ``max_stars`` caps the
    detections); ``--camera``: a frame of another size is one error line naming the file."""
    pipeline = tmp_path / "pipeline.toml"
    pipeline.write_text('[pipeline]\nsolver = "starenv.agents.solve:SvdSolver"\n[pipeline.options.detector]\n'
                        "max_stars = 30\n")
    out = tmp_path / "out.json"
    assert main(["solve", str(FRAMES[0]), "--camera", str(DATA / "tetra3_camera.toml"), "--pipeline", str(pipeline),
                 "--epoch", str(EPOCH), "--json", str(out)]) == 0
    (record,) = json.loads(out.read_text())
    assert record["solved"] and record["stars_detected"] == 30
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((48, 64), np.uint8))
    assert main(["solve", str(small), "--camera", str(DATA / "tetra3_camera.toml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(small) in err[0] and "64 x 48 px" in err[0]
