"""The binned read-out (block means drawn without the whole frame) against the whole frame's read-out, and the
network inputs centred on a star that datasets and the identifier build with it."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import ks_2samp

from starenv.agents.identify.network_model import MainStarConfig
from starenv.datasets import load_spec, sample
from starenv.datasets.preprocess import network_input, recentred, shifted
from starenv.sim.imager import Detector, DetectorSpec
from starenv.sim.render import StarSignal

BLOCK = 16
SIDE = 128  # px: 8 x 8 blocks
PAPER_002 = DetectorSpec(read_noise_e=10.0, dark_current_e_per_s=30.0, gain_e_per_dn=4.0, bias_dn=100.0,
                         full_well_e=30000.0, adc_bits=12, hot_pixel_fraction=2e-3, cosmic_ray_rate_per_cm2_s=50.0)


def _star_signal() -> StarSignal:
    """A star bright enough to saturate its core pixels (block (2, 3)) and a faint one (block (6, 1))."""
    yy, xx = np.mgrid[0:SIDE, 0:SIDE]
    image = (2e6 * np.exp(-((xx - 50.3) ** 2 + (yy - 40.7) ** 2) / 2) / (2 * np.pi)
             + 3e3 * np.exp(-((xx - 20.0) ** 2 + (yy - 100.0) ** 2) / 2) / (2 * np.pi))
    index = np.flatnonzero(image.ravel() > 1e-3)
    return StarSignal(index, image.ravel()[index].astype(np.float32), (SIDE, SIDE))


def _draws(n: int) -> tuple[np.ndarray, np.ndarray]:
    det = Detector(PAPER_002, SIDE, SIDE, 12e-6, 3.0, np.random.default_rng(1))
    signal, rng = _star_signal(), np.random.default_rng(2)
    whole = np.array([det.read_out(signal, 0.092, rng).astype(np.float64)
                      .reshape(SIDE // BLOCK, BLOCK, SIDE // BLOCK, BLOCK).mean(axis=(1, 3)) for _ in range(n)])
    binned = np.array([det.read_out_binned(signal, 0.092, rng, BLOCK) for _ in range(n)])
    return whole, binned


def test_block_means_are_the_whole_frames_in_distribution():
    """Each block's mean from the binned read-out and from the whole frame (1500 draws each): a saturated star's
    block, a faint star's and background blocks (some with hot pixels) pass a two-sample KS test at the 1e-3 level,
    and a background block's mean and variance are the closed form's (floor of a normal: E - 1/2, var + 1/12) within
    5 standard errors."""
    whole, binned = _draws(1500)
    for row, col in [(2, 3), (6, 1), (0, 0), (7, 7), (4, 5)]:
        assert ks_2samp(whole[:, row, col], binned[:, row, col]).pvalue > 1e-3, (row, col)
    lam = (3.0 + 30.0) * 0.092
    mean, var = (lam / 4.0 + 100.0 - 0.5), ((lam + 100.0) / 16.0 + 1.0 / 12.0) / BLOCK**2
    det = Detector(PAPER_002, SIDE, SIDE, 12e-6, 3.0, np.random.default_rng(1))
    busy = np.zeros(SIDE * SIDE, bool)
    busy[np.concatenate([_star_signal().index, det.hot_index])] = True
    quiet = ~busy.reshape(SIDE // BLOCK, BLOCK, SIDE // BLOCK, BLOCK).any(axis=(1, 3))
    values = binned[:, quiet]  # blocks of background alone, bar cosmic rays
    values = values[np.abs(values - mean) < 10 * np.sqrt(var)]
    assert abs(values.mean() - mean) < 5 * np.sqrt(var / values.size)
    assert abs(values.var() / var - 1) < 5 * np.sqrt(2 / values.size)


@pytest.mark.parametrize("spec, block, message", [
    (DetectorSpec(blooming=True), 16, "blooming"),
    (DetectorSpec(read_noise_e=0.5, dark_current_e_per_s=1.0), 16, "exact Poisson path"),
    (DetectorSpec(), 24, "do not tile"),
])
def test_the_binned_read_out_refuses_what_its_closed_form_does_not_hold_for(spec, block, message):
    det = Detector(spec, SIDE, SIDE, 12e-6, 3.0, np.random.default_rng(1))
    with pytest.raises(ValueError, match=message):
        det.read_out_binned(_star_signal(), 0.092, np.random.default_rng(0), block)


SKY = {"name": "sky", "kind": "main_star", "scenario": "paper_002", "samples": 4, "shard_size": 4, "seed": 11,
       "input_size": 64, "centre": "main_star", "pointing": {"mag_limit": 6.0, "offset_deg": 5.0},
       "rates": {"two_axis_dps": [0.0, 6.0], "roll_dps": [0.0, 6.0]}}


def test_a_binned_sample_is_the_frame_samples_draws_read_out_another_way():
    """Same spec but the read-out: the same main star (label, attitude) sits at the input's centre in both, and the
    inputs differ by read noise alone: the difference's mean over the input is within 5 of its standard errors."""
    frame, binned = load_spec(SKY), load_spec({**SKY, "readout": "binned"})
    assert frame.digest != binned.digest
    for index in range(3):
        a, b = sample(frame, index), sample(binned, index)
        assert a["label"] == b["label"] and np.array_equal(a["attitude"], b["attitude"])
        diff = (a["image"] - b["image"]).astype(np.float64)
        assert abs(diff.mean()) < 5 * diff.std() / np.sqrt(diff.size)


def test_specs_that_leave_readout_and_centre_out_keep_their_digest():
    plain = {k: v for k, v in SKY.items() if k != "centre"}
    assert load_spec(plain).digest == load_spec({**plain, "readout": "frame", "centre": "frame"}).digest
    assert "readout" not in load_spec(plain).to_dict()


@settings(max_examples=60, deadline=None)
@given(x=st.floats(-0.5, 1023.49), y=st.floats(-0.5, 1023.49))
def test_recentring_puts_the_centres_block_in_the_middle(x, y):
    """One lit pixel of a 1024 px frame: after recentring on it the input's only lit pixel is (32, 32) of 64."""
    frame = np.full((1024, 1024), 100, np.uint16)
    frame[int(np.floor(y + 0.5)), int(np.floor(x + 0.5))] = 4000
    image = network_input(frame, 64, (x, y))
    assert np.argwhere(image > 0).tolist() == [[32, 32]]
    assert np.array_equal(recentred(network_input(frame, 64), frame.shape, (x, y)), image)


@given(rows=st.integers(-70, 70), cols=st.integers(-70, 70))
def test_a_shift_and_its_inverse_keep_the_overlap_and_zero_the_rest(rows, cols):
    image = np.arange(1, 64 * 64 + 1, dtype=np.float32).reshape(64, 64)
    back = shifted(shifted(image, rows, cols), -rows, -cols)
    keep = np.zeros_like(image, bool)
    keep[max(-rows, 0): max(64 - max(rows, 0), 0), max(-cols, 0): max(64 - max(cols, 0), 0)] = True
    assert np.array_equal(back[keep], image[keep]) and not back[~keep].any()


def test_the_configs_centre_is_optional_in_old_manifests_and_checked():
    d = MainStarConfig(n_classes=10, input_size=64).to_dict()
    assert "centre" not in d and MainStarConfig.from_dict(d).centre == "frame"
    assert MainStarConfig.from_dict({**d, "centre": "main_star"}).centre == "main_star"
    with pytest.raises(ValueError, match="centre: expected one of frame, main_star"):
        MainStarConfig(n_classes=10, centre="star")
