"""Paper 002's network on the sensor as the env delivers its frames: one preprocessing for training and inference,
off-centre boresights labelled by the star nearest the centre, the training camera checked at reset, and attitude
hypotheses built from a main star anywhere in the frame."""

from pathlib import Path

import numpy as np
import pytest
import torch

from starenv.agents.detect.centroid import CentroidDetector
from starenv.agents.identify.network import WEIGHTS_DIR, NetworkIdentifier
from starenv.datasets import load_spec, sample
from starenv.datasets.preprocess import lower_median, network_input
from starenv.datasets.samples import context, draw, motion_table, navigation_stars, render
from starenv.env import StarSensorEnv
from starenv.sim.sky import load_catalog

OFFSET_DEG = 3.0


def _spec(**pointing):
    """Paper_002's own 1024 px sensor, boresights off the main star, the classes around Orion (a small cone keeps
    the catalogue queries short)."""
    return load_spec({"name": "sensor", "kind": "main_star", "scenario": "paper_002", "samples": 100, "seed": 4,
                      "input_size": 256,
                      "pointing": {"mag_limit": 6.0, "center_ra_deg": 83.8, "center_dec_deg": -5.4,
                                   "radius_deg": 20.0, "offset_deg": OFFSET_DEG, **pointing},
                      "rates": {"two_axis_dps": [0.0, 4.0], "directions": 0, "roll_dps": [0.0, 6.0]}})


@pytest.mark.parametrize("n", [1, 2, 7, 4096])
def test_lower_median_is_torch_median(n):
    values = np.random.default_rng(n).normal(100.0, 5.0, (3, n)).astype(np.float32)
    values[:, : n // 3] = np.round(values[:, : n // 3])  # ties too
    assert np.array_equal(lower_median(values), torch.from_numpy(values).median(dim=1).values.numpy())


def test_network_input_is_the_block_mean_less_its_median():
    """Square blocks of max(H, W) / size px; a frame that is not square sits at the input's centre, zeros around."""
    frame = np.random.default_rng(0).integers(0, 4096, (2, 96, 64)).astype(np.uint16)  # non-square, two frames
    got = network_input(frame, 24)  # 4 px blocks: 24 rows x 16 columns of them
    blocks = frame.astype(np.float64).reshape(2, 24, 4, 16, 4).mean(axis=(2, 4))  # independent: float64 means
    middle = np.sort(blocks.reshape(2, -1), axis=1)[:, (24 * 16 - 1) // 2]
    want = np.zeros((2, 24, 24), dtype=np.float32)
    want[:, :, 4:20] = blocks.astype(np.float32) - middle.astype(np.float32)[:, None, None]
    assert got.dtype == np.float32 and got.shape == (2, 24, 24)
    assert np.array_equal(got, want)
    square = frame[:, :64, :]
    assert np.array_equal(network_input(square, 16)[0], network_input(square[0], 16))
    with pytest.raises(ValueError, match="square blocks"):
        network_input(frame, 20)  # 96 / 20 px is no whole block
    with pytest.raises(ValueError, match="square blocks"):
        network_input(frame[:, :, :63], 24)  # 4 px blocks do not tile 63 columns


def test_a_centre_lands_on_the_inputs_centre_block_in_a_frame_that_is_not_square():
    frame = np.zeros((96, 64), dtype=np.uint16)
    for x, y in [(37, 61), (0, 0), (63, 95), (2, 50)]:
        frame[:] = 0
        frame[y, x] = 4000
        got = network_input(frame, 24, centre=(x + 0.3, y - 0.4))  # within the same pixel's block
        assert got[12, 12] == 4000 / 16 and np.count_nonzero(got) == 1


def test_a_local_background_takes_out_a_sloping_sky_and_leaves_a_star():
    """A background linear in x and y: away from the edges each block's 5 x 5 median is that block's own level (the
    median of values symmetric about it; the star's block lies above all 25 of them), so the local input there is
    exactly the star's block mean and zero elsewhere; the frame's median leaves the slope, hundreds of DN."""
    rows, cols = np.mgrid[0:192, 0:256]
    frame = (3000 + cols + rows).astype(np.uint16)  # block means step 16 DN a block: +-64 DN over a 5 x 5 window
    frame[100:102, 130:132] += 8192  # a star wholly in block (6, 8): its block mean rises by 128 DN
    local = network_input(frame, 16, background="local")[2:14]  # 12 x 16 blocks at rows 2..13 of the 16 x 16 input
    inner = local[2:-2, 2:-2]
    want = np.zeros_like(inner)
    want[6 - 2, 8 - 2] = 128.0
    assert np.array_equal(inner, want)
    flat = network_input(frame, 16)[2:14]
    assert np.abs(flat).max() > 128  # the slope left in: more than the star
    with pytest.raises(ValueError, match="background"):
        network_input(frame, 16, background="mean")


def test_a_sample_is_the_env_frame_preprocessed():
    """The training image of sample i is the env's 1024 px frame of the same motion and noise seed, through the
    identifier's own preprocessing, bit for bit (a clean sample: the generator renders the catalogue unedited)."""
    spec = _spec()
    for index in range(2):
        params = draw(spec, index)
        assert params["variant"] == "clean"
        env = StarSensorEnv(spec.load_scenario().data, overrides={"motion": motion_table(context(spec).scenario,
                                                                                          params)})
        env.sensor.reset(params["sensor_seed"])
        frame = env.sensor.next_frame().heads[0].image
        assert frame.shape == (1024, 1024)
        assert np.array_equal(sample(spec, index)["image"], network_input(frame, 256))


def test_a_sample_of_a_camera_that_is_not_square_is_its_env_frame_centred_on_the_main_star():
    """The real camera's twin (1024 x 768 px, datasets/tetra3_twin_sky.toml read out whole, no magnitude noise): the
    training image is the env's frame through the identifier's preprocessing, centred on the main star's block as the
    truth places it, bit for bit, and that block holds the main star."""
    root = Path(__file__).resolve().parent.parent
    twin = load_spec(root / "datasets" / "tetra3_twin_sky.toml").to_dict()
    spec = load_spec({**twin, "readout": "frame", "samples": 40,
                      "stars": {**twin["stars"], "magnitude_sigma": 0.0}})  # the env's sky, unedited
    clean = [i for i in range(40) if draw(spec, i)["variant"] == "clean"][:2]
    assert clean
    for index in clean:
        params = draw(spec, index)
        env = StarSensorEnv(spec.load_scenario().data, overrides={"motion": motion_table(context(spec).scenario,
                                                                                          params)})
        env.sensor.reset(params["sensor_seed"])
        head = env.sensor.next_frame().heads[0]
        assert head.image.shape == (768, 1024)
        hip = navigation_stars(spec)[0][params["main"]]
        xy = head.truth.xy_centroid[head.truth.catalog_id == hip][0]
        got = sample(spec, index)["image"]
        assert np.array_equal(got, network_input(head.image, 64, tuple(xy)))
        assert got[32, 32] > 5 * np.median(np.abs(got[got != 0]))  # a navigation star's block: far above the noise


def test_off_centre_boresights_are_labelled_by_the_nearest_navigation_star():
    spec = _spec()
    sc = context(spec).scenario
    mounting = sc.heads[0].camera.mounting
    classes = navigation_stars(spec)[0]
    sky = load_catalog(6.0, sc.epoch)  # every navigation star of the sky, searched by brute force
    offsets = []
    for index in range(20):
        params = draw(spec, index)
        boresight = (mounting * params["attitude"]).inv().apply([0.0, 0.0, 1.0])
        nearest = sky.hip[np.argmax(sky.unit @ boresight)]
        assert nearest == classes[params["main"]]
        main_unit = sky.unit[np.searchsorted(sky.hip, nearest)]
        offsets.append(np.degrees(np.arccos(np.clip(main_unit @ boresight, -1.0, 1.0))))
    assert max(offsets) <= OFFSET_DEG
    # uniform in the part of the cap nearest the star: almost never within a pixel (0.012 deg) of it
    assert min(offsets) > 0.012


def test_a_camera_other_than_the_training_one_is_refused():
    sc = _spec().load_scenario()
    agent = NetworkIdentifier("paper002_orion")  # a shipped run by name: 128 x 128 px, 12 deg
    assert agent.weights == WEIGHTS_DIR / "paper002_orion"
    with pytest.raises(ValueError, match=r"trained for a 128 x 128 px, 11.99 x 11.99 deg camera; head 0 is "
                                         r"1024 x 1024 px, 11.99 x 11.99 deg"):
        agent.reset([sc.heads[0].calibrated], load_catalog(sc.mag_limit, sc.epoch))


def test_a_main_star_anywhere_gives_the_attitude_among_the_hypotheses():
    """Given the true main star as the only candidate, the hypotheses built from the detections of a 1024 px frame
    (its boresight up to 3 deg off the star, 0-4 deg/s) hold the true attitude: within 0.1 deg, 8.5 px at this plate
    scale, far above the centroid errors the two detections that fix it carry."""
    spec = _spec()
    sc = spec.load_scenario()
    cam = sc.heads[0].calibrated
    agent = NetworkIdentifier("paper002_orion")
    agent.manifest = dict(agent.manifest, camera={"width": 1024, "height": 1024,
                                                  "fov_deg": [float(np.degrees(a)) for a in cam.fov]})
    agent.reset([cam], load_catalog(sc.mag_limit, sc.epoch))
    detector = CentroidDetector(psf_sigma_px=sc.heads[0].psf_sigma_px, max_stars=30)
    classes = navigation_stars(spec)[0]
    found = 0
    for index in range(6):
        params = draw(spec, index)
        _, frame = render(spec, params)
        det = detector.detect(frame.heads[0].image, cam).xy
        centre = np.argsort(np.hypot(det[:, 0] - cam.cx, det[:, 1] - cam.cy))[: agent.centre_stars]
        hypotheses = agent._hypotheses(cam, det, [(int(classes[params["main"]]), centre)])
        errors = [np.degrees((att * params["attitude"].inv()).magnitude()) for _, att in hypotheses]
        found += int(min(errors, default=180.0) < 0.1)
    assert found >= 5  # one frame may lack the main star among the detections nearest the centre

