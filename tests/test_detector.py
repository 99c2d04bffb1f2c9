from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from starenv.sim.drops import DropChannel, DropModel
from starenv.sim.imager import Detector, DetectorSpec
from starenv.sim.render import StarSignal

QUIET = {"hot_pixel_fraction": 0.0, "cosmic_ray_rate_per_cm2_s": 0.0}


def signal(shape, rows, cols, electrons):
    """Sparse signal of ``electrons`` on every pixel of the given row and column ranges."""
    idx = (np.arange(*rows)[:, None] * shape[1] + np.arange(*cols)).ravel()
    return StarSignal(idx, np.full(idx.size, electrons, np.float32), shape)


def nothing(shape=(256, 256)):
    return StarSignal(np.zeros(0, np.int64), np.zeros(0, np.float32), shape)


def make(spec, bg=0.0, shape=(256, 256), seed=0):
    return Detector(spec, shape[1], shape[0], 10e-6, bg, np.random.default_rng(seed))


@pytest.mark.parametrize(
    ("bg", "dark", "read", "gain"),
    [
        (500.0, 20.0, 8.0, 2.0),  # large background: the one-normal-per-pixel path
        (0.0, 300.0, 0.0, 0.5),  # no read noise, small mean: the exact Poisson path
        (0.0, 50.0, 3.0, 1.0),  # skewed sum: exact Poisson plus read noise
    ],
)
def test_dark_frame_mean_and_variance_match_the_noise_model(bg, dark, read, gain):
    exposure = 0.1
    spec = DetectorSpec(read_noise_e=read, dark_current_e_per_s=dark, gain_e_per_dn=gain, bias_dn=200, **QUIET)
    det = make(spec, bg)
    frames = np.stack([det.read_out(nothing(), exposure, np.random.default_rng(i)) for i in range(4)]).astype(float)
    lam = (bg + dark) * exposure
    # DN = floor(e / g + bias): the floor takes 1/2 DN off the mean and adds 1/12 DN^2 of variance.
    expected_mean = 200 + lam / gain - 0.5
    expected_var = (lam + read**2) / gain**2 + 1 / 12
    assert frames.mean() == pytest.approx(expected_mean, rel=0.01)
    assert frames.var(axis=(1, 2)).mean() == pytest.approx(expected_var, rel=0.03)


def test_fast_path_is_taken_only_when_the_sum_is_nearly_gaussian():
    assert make(DetectorSpec(read_noise_e=8.0, **QUIET), 500.0).background(0.1)[1] is not None
    assert make(DetectorSpec(read_noise_e=0.0, dark_current_e_per_s=300.0, **QUIET)).background(0.1)[1] is None


def test_star_signal_is_poisson_and_saturates_at_full_well_and_adc():
    spec = DetectorSpec(read_noise_e=0.0, dark_current_e_per_s=0.0, gain_e_per_dn=1.0, bias_dn=0, adc_bits=16,
                        full_well_e=5000.0, **QUIET)
    det = make(spec, shape=(64, 64))
    patch = signal((64, 64), (10, 14), (10, 14), 1000.0)
    frames = np.stack([det.read_out(patch, 0.1, np.random.default_rng(i)) for i in range(300)]).astype(float)
    px = frames[:, 10:14, 10:14]
    assert px.mean() == pytest.approx(1000, rel=0.003)  # gain 1: the floor of an integer count is exact
    assert px.var() == pytest.approx(1000, rel=0.08)
    assert frames[:, :10].max() == 0
    bright = signal((64, 64), (0, 2), (0, 2), 1e6)
    assert (det.read_out(bright, 0.1, np.random.default_rng(0))[:2, :2] == 5000).all()
    small_adc = make(DetectorSpec(read_noise_e=0.0, dark_current_e_per_s=0.0, gain_e_per_dn=1.0, bias_dn=0,
                                  adc_bits=8, **QUIET), shape=(64, 64))
    assert (small_adc.read_out(bright, 0.1, np.random.default_rng(0))[:2, :2] == 255).all()


def test_hot_pixels_are_a_fixed_pattern():
    spec = DetectorSpec(read_noise_e=1.0, dark_current_e_per_s=0.0, gain_e_per_dn=1.0, hot_pixel_fraction=1e-3,
                        hot_pixel_dark_e_per_s=1e4, cosmic_ray_rate_per_cm2_s=0.0)
    det = make(spec, shape=(512, 512))
    assert 262 * 0.7 < len(det.hot_index) < 262 * 1.3  # binomial(262144, 1e-3)
    a = det.read_out(nothing(det.shape), 1.0, np.random.default_rng(1)).ravel()
    b = det.read_out(nothing(det.shape), 1.0, np.random.default_rng(2)).ravel()
    hot_a = set(np.flatnonzero(a > 200))
    assert hot_a == set(np.flatnonzero(b > 200))
    assert hot_a <= set(det.hot_index.tolist())


def test_cosmic_ray_charge_matches_rate_times_area_times_mean_deposit():
    spec = DetectorSpec(read_noise_e=0.0, dark_current_e_per_s=0.0, gain_e_per_dn=1.0, bias_dn=0, adc_bits=16,
                        full_well_e=1e6, hot_pixel_fraction=0.0, cosmic_ray_rate_per_cm2_s=1000.0,
                        cosmic_ray_electrons=3000.0)
    det = make(spec, shape=(256, 256))  # 2.56 mm x 2.56 mm = 0.065536 cm^2
    totals = [det.read_out(nothing(det.shape), 0.1, np.random.default_rng(i)).sum(dtype=np.float64) for i in range(100)]
    expected = 1000.0 * 0.065536 * 0.1 * 3000.0 * np.exp(0.5**2 / 2)  # log-normal mean
    assert np.mean(totals) == pytest.approx(expected, rel=0.05)


def test_same_seed_same_frame():
    det = make(DetectorSpec(), 50.0)
    a = det.read_out(nothing(det.shape), 0.05, np.random.default_rng(7))
    b = det.read_out(nothing(det.shape), 0.05, np.random.default_rng(7))
    assert a.dtype == np.uint16 and np.array_equal(a, b)


@pytest.mark.parametrize("spec", [DetectorSpec(), DetectorSpec(read_noise_e=0.0, dark_current_e_per_s=300.0)],
                         ids=["gaussian", "poisson"])
def test_background_drawn_ahead_gives_the_same_frame(spec):
    # draw_background on another thread, then read_out with its future: the frame read_out draws alone, bit for bit,
    # on both the one-normal-a-pixel path and the exact Poisson path (stars, hot pixels and cosmic rays come after
    # the background in the stream).
    det = make(spec, 50.0)
    star = signal(det.shape, (100, 104), (60, 66), 3000.0)
    alone = det.read_out(star, 0.05, np.random.default_rng(7))
    rng = np.random.default_rng(7)
    with ThreadPoolExecutor(1) as executor:
        ahead = det.read_out(star, 0.05, rng, background=executor.submit(det.draw_background, 0.05, rng))
    np.testing.assert_array_equal(ahead, alone)


@pytest.mark.parametrize(("field", "value"), [("adc_bits", 0), ("adc_bits", 17), ("read_noise_e", float("nan")),
                                               ("gain_e_per_dn", 0.0), ("full_well_e", -1.0)])
def test_bad_detector_input_names_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        DetectorSpec(**{field: value})


def test_independent_drops_hit_the_configured_rate():
    ch = DropChannel(DropModel(probability=0.2))
    rng = np.random.default_rng(3)
    drops = np.array([ch.dropped(rng) for _ in range(20000)])
    assert drops.mean() == pytest.approx(0.2, abs=0.01)
    # memoryless: P(drop | previous drop) = P(drop)
    assert drops[1:][drops[:-1]].mean() == pytest.approx(0.2, abs=0.02)


def test_bursty_drops_have_the_markov_rate_and_burst_length():
    model = DropModel(probability=0.0, p_good_to_bad=0.02, p_bad_to_good=0.25, drop_bad=1.0)
    assert model.drop_rate == pytest.approx(0.02 / 0.27)
    ch = DropChannel(model)
    rng = np.random.default_rng(4)
    drops = np.array([ch.dropped(rng) for _ in range(50000)])
    assert drops.mean() == pytest.approx(model.drop_rate, rel=0.08)
    edges = np.flatnonzero(np.diff(np.r_[0, drops.astype(int), 0]))
    bursts = edges[1::2] - edges[::2]
    assert bursts.mean() == pytest.approx(1 / 0.25, rel=0.08)


def test_bad_drop_probability_names_the_field():
    with pytest.raises(ValueError, match="drops.probability"):
        DropModel(probability=1.5)
