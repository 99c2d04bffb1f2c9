"""Image restoration algorithms (no agent logic): Richardson-Lucy on a frame or on a batch of patches, and Wiener.

Convolution convention: ``'same'`` mode with zero padding, as ``scipy.signal.fftconvolve(mode="same")``: a kernel of
size ``k`` has its origin at index ``(k - 1) // 2`` along each axis (the centre of an odd kernel, as
:func:`starenv.psf.path_kernel` builds them).  Kernels are normalised to sum 1 on entry.

Richardson-Lucy (seed 000, Eq. 26; seed 001, Eq. 24) for ``g = f (x) h + b`` with Poisson noise::

    f <- f * [ (g / (f (x) h + b + eps)) (*) h ]        ((*): correlation, convolution with h flipped)

Starting from a positive ``f`` and ``g >= 0`` every iterate is non-negative (the correction factor is clipped at 0
against FFT round-off), and with ``b = 0`` and an odd-sized
kernel the flux ``sum f`` equals ``sum g`` after every iteration (to ``eps``): correlation is then the exact adjoint
of the 'same'-mode convolution, so the edge terms cancel.  (With an even size the two origins differ by a pixel.)
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy import fft

from starenv import checks

EPS = 1e-12  # added to the model image before dividing (skimage's value)
THREADED_FFT_PX = 256 * 256  # transforms of at least this many pixels per image use every core


def _workers(shape: tuple[int, int]) -> int:
    """scipy.fft workers for transforms of ``shape``: all cores for large images; one for small ones, where pocketfft's
    threads cost more than they save (measured: a (108, 48, 48) batch 1.5x slower on 2 threads than on one)."""
    return -1 if shape[0] * shape[1] >= THREADED_FFT_PX else 1


def _image(name: str, value, ndim: int) -> np.ndarray:
    arr = checks.finite(name, value)
    if arr.ndim != ndim or min(arr.shape) == 0:
        raise ValueError(f"{name} must be a non-empty {ndim}-D array, got shape {arr.shape}")
    return arr


def _kernels(psf: np.ndarray, name: str) -> np.ndarray:
    if np.any(psf < 0):
        raise ValueError(f"{name} must be non-negative")
    total = psf.sum(axis=(-2, -1), keepdims=True)
    if np.any(total <= 0):
        raise ValueError(f"{name} must have a positive sum")
    return psf / total


class _SameConvolver:
    """'same'-mode (or circular) convolution and correlation with fixed kernels (..., kh, kw) on images (..., h, w),
    by FFT."""

    def __init__(self, shape: tuple[int, int], psf: np.ndarray, circular: bool = False):
        h, w = shape
        kh, kw = psf.shape[-2:]
        if circular:  # periodic images: transforms of the image's own size, the kernel's origin moved to (0, 0)
            if kh > h or kw > w:
                raise ValueError(f"psfs shape {(kh, kw)} must not exceed the patches' {(h, w)} for circular mode")
            self.shape, self.start = (h, w), (0, 0)
            origin = ((kh - 1) // 2, (kw - 1) // 2)
            flipped_origin = (kh // 2, kw // 2)
            self.otf = self._circular_otf(psf, shape, origin)
            self.otf_flipped = self._circular_otf(psf[..., ::-1, ::-1], shape, flipped_origin)
        else:
            self.shape = (fft.next_fast_len(h + kh - 1, real=True), fft.next_fast_len(w + kw - 1, real=True))
            self.start = ((kh - 1) // 2, (kw - 1) // 2)
            self.otf = fft.rfft2(psf, self.shape, workers=_workers(self.shape))
            self.otf_flipped = fft.rfft2(psf[..., ::-1, ::-1], self.shape, workers=_workers(self.shape))
        self.size = (h, w)
        self.workers = _workers(self.shape)

    @staticmethod
    def _circular_otf(psf: np.ndarray, shape: tuple[int, int], origin: tuple[int, int]) -> np.ndarray:
        padded = np.zeros((*psf.shape[:-2], *shape), dtype=psf.dtype)
        padded[..., : psf.shape[-2], : psf.shape[-1]] = psf
        return fft.rfft2(np.roll(padded, (-origin[0], -origin[1]), axis=(-2, -1)), workers=_workers(shape))

    def _apply(self, x: np.ndarray, otf: np.ndarray) -> np.ndarray:
        spectrum = fft.rfft2(x, self.shape, workers=self.workers) * otf
        full = fft.irfft2(spectrum, self.shape, workers=self.workers)
        (r, c), (h, w) = self.start, self.size
        return full[..., r : r + h, c : c + w]

    def convolve(self, x: np.ndarray) -> np.ndarray:
        return self._apply(x, self.otf)

    def correlate(self, x: np.ndarray) -> np.ndarray:
        """Convolution with the flipped kernel (the adjoint of :meth:`convolve` up to the kernel origin)."""
        return self._apply(x, self.otf_flipped)


def richardson_lucy(image, psf, iterations: int, *, background=0.0, initial=None,
                    callback: Callable[[int, np.ndarray], bool] | None = None) -> np.ndarray:
    """Richardson-Lucy deconvolution of a whole frame (float64 result, same shape as ``image``).

    ``image`` (H, W) >= 0 (DN or electrons, raw: the background is modelled, not subtracted); ``psf`` (kh, kw)
    non-negative, normalised here, origin as in the module docstring; ``iterations`` >= 0; ``background``: the
    level ``b`` (scalar or (H, W)) added to the model image; ``initial``: the starting estimate (scalar or (H, W),
    > 0); None: the flat image ``max(mean(image - b), eps)``.  ``callback(iteration, estimate)`` is called after
    every iteration (1-based) and stops the iterations by returning True.
    """
    g = _image("image", image, 2)
    if np.any(g < 0):
        raise ValueError("image must be non-negative (Richardson-Lucy models Poisson counts)")
    h = _kernels(_image("psf", psf, 2), "psf")
    n_iter = checks.integer("iterations", iterations, 0, 100000)
    b = checks.finite("background", background)
    if np.any(b < 0) or b.shape not in ((), g.shape):
        raise ValueError(f"background must be a non-negative scalar or an array of shape {g.shape}")
    if initial is None:
        f = np.full(g.shape, max(float(np.mean(g - b)), EPS))
    else:
        f0 = checks.finite("initial", initial)
        if np.any(f0 <= 0) or f0.shape not in ((), g.shape):
            raise ValueError(f"initial must be a positive scalar or an array of shape {g.shape}")
        f = np.broadcast_to(f0, g.shape).astype(np.float64)
    conv = _SameConvolver(g.shape, h)
    for k in range(1, n_iter + 1):
        f = f * np.maximum(conv.correlate(g / (conv.convolve(f) + b + EPS)), 0.0)
        if callback is not None and callback(k, f):
            break
    return f


def richardson_lucy_batch(patches, psfs, iterations: int, *, background=0.0, circular: bool = False) -> np.ndarray:
    """Richardson-Lucy on a stack of patches, each with its own kernel, all at once (batched FFTs).

    ``patches`` (b, h, w) >= 0; ``psfs`` (b, kh, kw) non-negative (normalised here; pad kernels of different sizes
    with zeros about a common centre); ``background`` scalar or (b,): each patch's level.  Each patch starts from its
    flat mean (as :func:`richardson_lucy` with ``initial=None``).  Computed in float32 when ``patches`` and ``psfs``
    are both float32 (half the cost of the transforms), else in float64.  ``circular``: convolve periodically on the
    patch itself (transforms of the patch size instead of patch + kernel - 1; for patches whose border holds only
    background, where the wrap-around is harmless).  Returns (b, h, w) in the working precision.
    """
    single = getattr(patches, "dtype", None) == np.float32 and getattr(psfs, "dtype", None) == np.float32
    g = _image("patches", patches, 3)
    if np.any(g < 0):
        raise ValueError("patches must be non-negative (Richardson-Lucy models Poisson counts)")
    h = _kernels(_image("psfs", psfs, 3), "psfs")
    if single:
        g, h = g.astype(np.float32), h.astype(np.float32)
    if len(h) != len(g):
        raise ValueError(f"psfs must hold one kernel per patch: {len(g)} patches, {len(h)} kernels")
    n_iter = checks.integer("iterations", iterations, 0, 100000)
    b = checks.finite("background", background)
    if np.any(b < 0) or b.shape not in ((), (len(g),)):
        raise ValueError(f"background must be a non-negative scalar or an array of shape ({len(g)},)")
    b = np.broadcast_to(b, (len(g),))[:, None, None].astype(g.dtype)
    f = np.broadcast_to(np.maximum((g - b).mean(axis=(1, 2), keepdims=True), EPS), g.shape).astype(g.dtype)
    if not isinstance(circular, bool):
        raise ValueError(f"circular must be True or False, got {circular!r}")
    conv = _SameConvolver(g.shape[1:], h, circular)
    for _ in range(n_iter):
        f = f * np.maximum(conv.correlate(g / (conv.convolve(f) + b + EPS)), 0.0)
    return f


def convolve_batch(images, psfs, *, circular: bool = False) -> np.ndarray:
    """Convolution of a stack of images (b, h, w) with kernels (b, kh, kw) (or one kernel (1, kh, kw) for all),
    'same' mode with zero padding or, with ``circular``, periodic on the image itself (kernels not normalised; float32
    when both inputs are float32, else float64)."""
    single = getattr(images, "dtype", None) == np.float32 and getattr(psfs, "dtype", None) == np.float32
    x = _image("images", images, 3)
    k = _image("psfs", psfs, 3)
    if len(k) not in (1, len(x)):
        raise ValueError(f"psfs must hold one kernel per image or a single one: {len(x)} images, {len(k)} kernels")
    if single:
        x, k = x.astype(np.float32), k.astype(np.float32)
    return _SameConvolver(x.shape[1:], k, circular).convolve(x)


def wiener(image, psf, nsr) -> np.ndarray:
    """Frequency-domain Wiener deconvolution: ``F = conj(H) G / (|H|^2 + nsr)`` (float64 (H, W)).

    ``H`` is the transfer function of ``psf`` (kh, kw; normalised here) on the image's grid with the kernel's origin
    (module docstring) moved to pixel (0, 0), so the restoration is circular (periodic image).  ``nsr`` >= 0 is the
    noise-to-signal power ratio, a scalar or per frequency (an (H, W // 2 + 1) array on ``scipy.fft.rfft2``'s grid).
    For odd kernels this is ``skimage.restoration.wiener`` with ``balance = nsr`` and ``reg = [[1]]``.
    """
    g = _image("image", image, 2)
    h = _kernels(_image("psf", psf, 2), "psf")
    rows, cols = g.shape
    kh, kw = h.shape
    if kh > rows or kw > cols:
        raise ValueError(f"psf shape {h.shape} must not exceed the image's {g.shape}")
    ratio = checks.finite("nsr", nsr)
    if np.any(ratio < 0) or ratio.shape not in ((), (rows, cols // 2 + 1)):
        raise ValueError(f"nsr must be a non-negative scalar or an array of shape {(rows, cols // 2 + 1)}")
    padded = np.zeros(g.shape)
    padded[:kh, :kw] = h
    padded = np.roll(padded, (-((kh - 1) // 2), -((kw - 1) // 2)), axis=(0, 1))
    otf = fft.rfft2(padded, workers=_workers(g.shape))
    power = np.abs(otf) ** 2
    if np.any(power + ratio == 0):
        raise ValueError("nsr must be positive where the psf's transfer function vanishes")
    spectrum = np.conj(otf) * fft.rfft2(g, workers=_workers(g.shape)) / (power + ratio)
    return fft.irfft2(spectrum, g.shape, workers=_workers(g.shape))
