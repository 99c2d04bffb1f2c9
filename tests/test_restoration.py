"""Richardson-Lucy and Wiener against scikit-image (an independent implementation) and closed forms."""

import numpy as np
import pytest
from scipy.signal import fftconvolve
from skimage.restoration import richardson_lucy as sk_richardson_lucy
from skimage.restoration import wiener as sk_wiener

from starenv.agents.restore.algorithms import convolve_batch, richardson_lucy, richardson_lucy_batch, wiener


def random_case(seed: int, shape=(48, 64), kernel=(7, 9)):
    rng = np.random.default_rng(seed)
    psf = rng.random(kernel)
    psf /= psf.sum()
    return rng.poisson(40.0, shape).astype(np.float64), psf


@pytest.mark.parametrize("kernel", [(7, 9), (6, 10), (1, 15), (21, 4)])
def test_richardson_lucy_matches_skimage(kernel):
    image, psf = random_case(1, kernel=kernel)
    want = sk_richardson_lucy(image, psf, 12, clip=False)  # float64, starts from 0.5, eps 1e-12
    got = richardson_lucy(image, psf, 12, initial=0.5)
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-9 * want.max())


def test_richardson_lucy_conserves_flux_and_stays_non_negative():
    image, psf = random_case(2)
    image[10:20, 5:30] = 0.0  # zeros in the data keep the iterates >= 0, never negative
    for n in (1, 5, 30):
        out = richardson_lucy(image, psf, n)
        assert out.sum() == pytest.approx(image.sum(), rel=1e-10)  # odd kernel: exact adjoint, flux kept
        assert out.min() >= 0.0


def test_richardson_lucy_recovers_a_blurred_point():
    # Noise-free blur of two points: RL moves the light back onto them (the exact solution is a fixed point).
    truth = np.zeros((40, 40))
    truth[12, 15] = 1000.0
    truth[27, 22] = 400.0
    psf = np.zeros((9, 9))
    psf[4, 1:8] = 1.0  # a 7 px horizontal trail
    psf = np.maximum(fftconvolve(psf, np.outer([1, 2, 1], [1, 2, 1]) / 16.0, mode="same"), 0.0)
    blurred = fftconvolve(truth, psf / psf.sum(), mode="same") + 5.0
    out = richardson_lucy(np.maximum(blurred, 0), psf, 500, background=5.0)
    assert out[12, 15] > 0.9 * 1000.0 and out[27, 22] > 0.9 * 400.0
    # Where the data equal the background, what is left of the flat start decays only slowly: ~1 % of the light.
    assert out.sum() == pytest.approx(1400.0, rel=0.02)


def test_callback_stops_early_and_sees_each_iterate():
    image, psf = random_case(3)
    seen = []

    def stop_at_four(k, estimate):
        seen.append(k)
        return k == 4

    out = richardson_lucy(image, psf, 50, callback=stop_at_four)
    assert seen == [1, 2, 3, 4]
    np.testing.assert_array_equal(out, richardson_lucy(image, psf, 4))


def test_batch_equals_one_patch_at_a_time():
    rng = np.random.default_rng(4)
    patches = rng.poisson(30.0, (5, 24, 32)).astype(np.float64)
    psfs = rng.random((5, 9, 7))
    background = np.array([0.0, 1.0, 2.0, 3.0, 4.0])
    got = richardson_lucy_batch(patches, psfs, 15, background=background)
    for i in range(5):
        want = richardson_lucy(patches[i], psfs[i], 15, background=background[i])
        np.testing.assert_allclose(got[i], want, rtol=1e-10, atol=1e-12)


def test_convolve_batch_same_and_circular_modes():
    rng = np.random.default_rng(8)
    images = rng.random((3, 20, 24))
    psfs = rng.random((3, 7, 5))
    same = convolve_batch(images, psfs)
    for i in range(3):
        np.testing.assert_allclose(same[i], fftconvolve(images[i], psfs[i], mode="same"), atol=1e-12)
    # Circular: the kernel's origin (3, 2) moved to (0, 0), products of the image-sized DFTs.
    padded = np.zeros((3, 20, 24))
    padded[:, :7, :5] = psfs
    otf = np.fft.rfft2(np.roll(padded, (-3, -2), axis=(1, 2)))
    want = np.fft.irfft2(np.fft.rfft2(images) * otf, (20, 24))
    np.testing.assert_allclose(convolve_batch(images, psfs, circular=True), want, atol=1e-12)
    # float32 in, float32 out (to float32 precision); one kernel for the whole stack.
    one = convolve_batch(images.astype(np.float32), psfs[:1].astype(np.float32), circular=True)
    assert one.dtype == np.float32
    np.testing.assert_allclose(one[2], convolve_batch(images[2:], psfs[:1], circular=True)[0], rtol=1e-5, atol=1e-5)


def test_circular_batch_equals_same_mode_away_from_the_border():
    # A trail well inside a patch with a flat background: periodic and zero-padded RL put the same light at the
    # same place (their flat remainders differ: zero padding starves the border, which spreads inwards).
    patches = np.full((2, 48, 48), 20.0)
    patches[:, 22:26, 14:34] += 50.0
    psfs = np.zeros((2, 9, 21))
    psfs[:, 4, :] = 1.0
    a = richardson_lucy_batch(patches, psfs, 10, background=20.0)
    b = richardson_lucy_batch(patches.astype(np.float32), psfs.astype(np.float32), 10, background=20.0,
                              circular=True)
    star = (slice(None), slice(20, 28), slice(18, 30))
    np.testing.assert_allclose(b[star].sum(axis=(1, 2)), a[star].sum(axis=(1, 2)), rtol=0.01)
    yy, xx = np.mgrid[20:28, 18:30]
    for img in (a[0], b[0]):
        w = img[20:28, 18:30]
        assert ((w * xx).sum() / w.sum(), (w * yy).sum() / w.sum()) == pytest.approx((23.5, 23.5), abs=0.05)


def test_wiener_matches_skimage_with_identity_regulariser():
    image, psf = random_case(5, kernel=(9, 5))
    want = sk_wiener(image, psf, 0.05, reg=np.array([[1.0]]), clip=False)
    np.testing.assert_allclose(wiener(image, psf, 0.05), want, rtol=1e-9, atol=1e-9 * np.abs(want).max())


def test_wiener_inverts_a_noise_free_circular_blur():
    rng = np.random.default_rng(6)
    truth = np.zeros((32, 32))
    truth[10, 7] = 1.0
    psf = rng.random((5, 5)) + 0.5  # no zero in its transfer function (positive, mostly DC)
    psf /= psf.sum()
    # Circular blur with the kernel's origin (2, 2): the delta lands spread around (10, 7).
    padded = np.zeros_like(truth)
    padded[:5, :5] = psf
    otf = np.fft.rfft2(np.roll(padded, (-2, -2), axis=(0, 1)))
    blurred = np.fft.irfft2(np.fft.rfft2(truth) * otf, truth.shape)
    np.testing.assert_allclose(wiener(blurred, psf, 1e-12), truth, atol=1e-6)
    # Per-frequency nsr: a ratio of 1 everywhere halves what |H| = 1 (the DC term) lets through.
    dc_only = wiener(np.ones((32, 32)), psf, np.ones((32, 17)))
    np.testing.assert_allclose(dc_only, 0.5, rtol=1e-12)


def test_bad_input_names_the_field():
    image, psf = random_case(7)
    with pytest.raises(ValueError, match="image"):
        richardson_lucy(-image, psf, 3)
    with pytest.raises(ValueError, match="psf"):
        richardson_lucy(image, -psf, 3)
    with pytest.raises(ValueError, match="iterations"):
        richardson_lucy(image, psf, 2.5)
    with pytest.raises(ValueError, match="background"):
        richardson_lucy(image, psf, 3, background=np.ones(3))
    with pytest.raises(ValueError, match="psfs"):
        richardson_lucy_batch(image[None], np.stack([psf, psf]), 3)
    with pytest.raises(ValueError, match="nsr"):
        wiener(image, psf, -1.0)
    with pytest.raises(ValueError, match="psf"):
        wiener(image[:4, :4], psf, 0.1)
