"""Image restoration algorithms (no agent logic): Richardson-Lucy on a frame or on a batch of patches, and Wiener.

Convolution convention: ``'same'`` mode with zero padding, as ``scipy.signal.fftconvolve(mode="same")``: a kernel of
size ``k`` has its origin at index ``(k - 1) // 2`` along each axis (the centre of an odd kernel, as
:func:`starenv.agents.restore.kernels.path_kernel` builds them).  Kernels are normalised to sum 1 on entry.

Richardson-Lucy (paper 000, Eq. 26; paper 001, Eq. 24) for ``g = f (x) h + b`` with Poisson noise::

    f <- f * [ (g / (f (x) h + b + eps)) (*) h ]        ((*): correlation, convolution with h flipped)

Starting from a positive ``f`` and ``g >= 0`` every iterate is non-negative (the correction factor is clipped at 0
against FFT round-off), and with ``b = 0`` and an odd-sized
kernel the flux ``sum f`` equals ``sum g`` after every iteration (to ``eps``): correlation is then the exact adjoint
of the 'same'-mode convolution, so the edge terms cancel.  (With an even size the two origins differ by a pixel.)
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
from scipy import fft
from scipy.signal import fftconvolve

from starenv import checks
from starenv.agents.blocks import frame_background
from starenv.sim.optics import Camera

EPS = 1e-12  # added to the model image before dividing (skimage's value)
THREADED_FFT_PX = 256 * 256  # transforms of at least this many pixels per image use every core


def _workers(shape: tuple[int, int]) -> int:
    """scipy.fft workers for transforms of ``shape``: all cores for large images; one for small ones, where pocketfft's
    threads cost more than they save (a transform of a few thousand pixels is shorter than the threads' hand-off)."""
    return -1 if shape[0] * shape[1] >= THREADED_FFT_PX else 1


def _image(name: str, value, ndim: int, single: bool = False) -> np.ndarray:
    """``value`` checked as a finite, non-empty ``ndim``-D array: float64, or kept float32 with ``single``."""
    if single:
        arr = np.asarray(value, dtype=np.float32)
        if not np.isfinite(arr).all():
            raise ValueError(f"{name} must be finite (no NaN or inf)")
    else:
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
            if kh % 2 and kw % 2:  # odd kernels: the flipped one is the kernel reflected about pixel (0, 0)
                self.otf_flipped = np.conj(self.otf)
            else:
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
        spectrum = fft.rfft2(x, self.shape, workers=self.workers)
        spectrum *= otf
        full = fft.irfft2(spectrum, self.shape, workers=self.workers, overwrite_x=True)
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


def richardson_lucy_batch(patches, psfs, iterations: int, *, background=0.0, circular: bool = False,
                          initial=None, callback: Callable[[int, np.ndarray], bool] | None = None) -> np.ndarray:
    """Richardson-Lucy on a stack of patches, each with its own kernel, all at once (batched FFTs).

    ``patches`` (b, h, w) >= 0; ``psfs`` (b, kh, kw) non-negative (normalised here; pad kernels of different sizes
    with zeros about a common centre); ``background`` scalar or (b,): each patch's level; ``initial``: the starting
    estimates (b, h, w) > 0, None: each patch's flat mean (as :func:`richardson_lucy`); ``callback(iteration,
    estimates)`` after every iteration (1-based) stops them all by returning True.  Computed in float32 when ``patches``
    and ``psfs`` are both float32 (half the cost of the transforms), else in float64.  ``circular``: convolve
    periodically on the patch itself (transforms of the patch size instead of patch + kernel - 1; for patches whose
    border holds only background, where the wrap-around is harmless).  Returns (b, h, w) in the working precision.
    """
    single = getattr(patches, "dtype", None) == np.float32 and getattr(psfs, "dtype", None) == np.float32
    g = _image("patches", patches, 3, single)
    if np.any(g < 0):
        raise ValueError("patches must be non-negative (Richardson-Lucy models Poisson counts)")
    h = _kernels(_image("psfs", psfs, 3, single), "psfs")
    if len(h) != len(g):
        raise ValueError(f"psfs must hold one kernel per patch: {len(g)} patches, {len(h)} kernels")
    n_iter = checks.integer("iterations", iterations, 0, 100000)
    b = checks.finite("background", background)
    if np.any(b < 0) or b.shape not in ((), (len(g),)):
        raise ValueError(f"background must be a non-negative scalar or an array of shape ({len(g)},)")
    b = np.broadcast_to(b, (len(g),))[:, None, None].astype(g.dtype)
    if initial is None:
        f = np.broadcast_to(np.maximum((g - b).mean(axis=(1, 2), keepdims=True), EPS), g.shape).astype(g.dtype)
    else:
        f = checks.finite("initial", initial)
        if f.shape != g.shape or np.any(f <= 0):
            raise ValueError(f"initial must be a positive array of shape {g.shape}")
        f = f.astype(g.dtype)
    if not isinstance(circular, bool):
        raise ValueError(f"circular must be True or False, got {circular!r}")
    conv = _SameConvolver(g.shape[1:], h, circular)
    floor = b + g.dtype.type(EPS)
    for k in range(1, n_iter + 1):
        model = conv.convolve(f)
        model += floor
        ratio = conv.correlate(np.divide(g, model, out=model))
        f = f * np.maximum(ratio, 0.0, out=ratio)
        if callback is not None and callback(k, f):
            break
    return f


def convolve_batch(images, psfs, *, circular: bool = False) -> np.ndarray:
    """Convolution of a stack of images (b, h, w) with kernels (b, kh, kw) (or one kernel (1, kh, kw) for all),
    'same' mode with zero padding or, with ``circular``, periodic on the image itself (kernels not normalised; float32
    when both inputs are float32, else float64)."""
    single = getattr(images, "dtype", None) == np.float32 and getattr(psfs, "dtype", None) == np.float32
    x = _image("images", images, 3, single)
    k = _image("psfs", psfs, 3, single)
    if len(k) not in (1, len(x)):
        raise ValueError(f"psfs must hold one kernel per image or a single one: {len(x)} images, {len(k)} kernels")
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


def checked_image(image, camera: Camera) -> np.ndarray:
    """``image`` as a finite 2-D array of the camera's shape (DN), else ValueError."""
    if not isinstance(image, np.ndarray) or image.ndim != 2:
        raise ValueError(f"image must be a 2-D array (DN), got {type(image).__name__}")
    if image.shape != (camera.height, camera.width):
        raise ValueError(f"image shape {image.shape} does not match the camera's {(camera.height, camera.width)}")
    if np.issubdtype(image.dtype, np.integer):  # a sensor's counts: finite, converted without the check
        return image.astype(np.float64)
    return checks.finite("image", image)


def resharpen(data: np.ndarray, estimate: np.ndarray, kernel: np.ndarray, psf_sigma_px: float) -> np.ndarray:
    """The frame with each blurred star replaced by its still image: ``g - f (x) h + f (x) G``.

    ``data`` g (..., H, W) the observed frame(s), ``estimate`` f the restored scene (background removed),
    ``kernel`` h (..., kh, kw) the blur it was restored with, G the Gaussian PSF of ``psf_sigma_px`` (px).  The
    residual ``g - f (x) h - b`` (pixel noise, what the model does not explain) is kept as observed, so the output has
    the frame's own noise and background, with no seam where only part of the frame was restored.
    """
    axes = (-2, -1)
    model = fftconvolve(estimate, kernel, mode="same", axes=axes)
    flat = estimate.reshape(-1, *estimate.shape[-2:])
    still = np.stack([cv2.GaussianBlur(x, (0, 0), psf_sigma_px, borderType=cv2.BORDER_REFLECT) for x in flat])
    return data - model + still.reshape(estimate.shape)


# Eq. 17: (dy, dx) of the three points of each tangent plane around (y, x).
PLANES = (
    ((0, -1), (0, 1), (1, 0)),
    ((-1, 0), (-1, 1), (0, 1)),
    ((-1, -1), (0, -1), (-1, 0)),
    ((1, 0), (0, 1), (1, 1)),
    ((-1, 0), (1, 0), (0, 1)),
    ((0, -1), (1, 0), (1, -1)),
    ((-1, 0), (1, 0), (0, -1)),
    ((0, -1), (-1, 0), (0, 1)),
)
NEIGHBOURS = tuple((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0))


def _distances(nb):
    """Eq. 17's eight signed distances, one array each, from ``nb(dy, dx)``: the neighbour values at (dy, dx)."""
    centre = nb(0, 0)
    for plane in PLANES:
        yield (nb(*plane[0]) + nb(*plane[1]) + nb(*plane[2]) - 3.0 * centre) / 3.0  # exactly 0 where flat


def _step(nb) -> np.ndarray:
    """Eq. 18's ``d_m``: of the eight distances, the one of smallest magnitude (the first on a tie)."""
    best = None
    for d in _distances(nb):
        best = d if best is None else np.where(np.abs(d) < np.abs(best), d, best)
    return best


def _energy(nb, step: np.ndarray, alpha: float) -> np.ndarray:
    centre = nb(0, 0)
    a = np.stack([np.abs(centre - nb(dy, dx)) ** alpha for dy, dx in NEIGHBOURS])
    return np.abs(step) + np.partition(a, 3, axis=0)[:4].sum(axis=0)


def _views(padded: np.ndarray, pad: int, shape: tuple[int, int], origin=(0, 0), stride: int = 1):
    """Neighbour accessor over padded images (last two axes): pixels ``origin + stride * (i, j)`` of a grid
    ``shape`` (H, W)."""
    oy, ox = origin
    h, w = shape

    def nb(dy, dx):
        y0, x0 = pad + oy + dy, pad + ox + dx
        return padded[..., y0 : y0 + stride * (h - 1) + 1 : stride, x0 : x0 + stride * (w - 1) + 1 : stride]

    return nb


def plane_distances(f: np.ndarray) -> np.ndarray:
    """Eq. 17: the signed distances (8, H, W) from each pixel to its eight tangent planes (edges replicated)."""
    f = np.asarray(f, dtype=np.float64)
    return np.stack(list(_distances(_views(np.pad(f, 1, mode="edge"), 1, f.shape))))


def nearest_plane_step(f: np.ndarray) -> np.ndarray:
    """Eq. 18: ``d_m`` (H, W), the Eq. 17 plane distance of smallest magnitude (edges replicated); ``f + d_m`` is
    the projection of each pixel onto its nearest tangent plane."""
    f = np.asarray(f, dtype=np.float64)
    return _step(_views(np.pad(f, 1, mode="edge"), 1, f.shape))


def gating_energy(f: np.ndarray, alpha: float = 1.0) -> np.ndarray:
    """Eqs. 19-23: ``E = |d_m|`` plus the sum of the 4 smallest ``|f - f_neighbour|^alpha`` (H, W)."""
    f = np.asarray(f, dtype=np.float64)
    nb = _views(np.pad(f, 1, mode="edge"), 1, f.shape)
    return _energy(nb, _step(nb), alpha)


def curvature_energy(f: np.ndarray) -> float:
    """The image's curvature energy ``sum |d_m|`` (grey levels), which :func:`curvature_filter` never raises."""
    return float(np.abs(nearest_plane_step(f)).sum())


def curvature_filter(image: np.ndarray, threshold: float | None = None, iterations: int = 3,
                     alpha: float = 1.0, threshold_sigma: float = 3.0) -> np.ndarray:
    """Paper 001's improved Gaussian-curvature filter (module docstring): float64 (..., H, W) from an image or a stack
    of images (each filtered alone, edges replicated).

    ``threshold``: the energy gate T in the image's units (None: ``threshold_sigma`` times the noise sigma of the
    image, of the whole stack for a stack, by :func:`~starenv.agents.blocks.frame_background`); ``iterations``:
    passes over the image; ``alpha``: exponent of the edge-preserving potential, 1 to 2.
    """
    image = checks.finite("image", image)
    if image.ndim < 2 or min(image.shape[-2:]) < 3:
        raise ValueError(f"image must be a 2-D array (or a stack of them) of at least 3 x 3 pixels, got shape "
                         f"{image.shape}")
    f = image.astype(np.float64).reshape(-1, *image.shape[-2:])
    iterations = checks.integer("iterations", iterations, 0, 1000)
    alpha = checks.in_range("alpha", alpha, 1.0, 2.0)
    if threshold is None:
        t = checks.non_negative("threshold_sigma", threshold_sigma) * frame_background(f)[1]
    else:
        t = checks.non_negative("threshold", threshold)
    h, w = f.shape[-2:]
    window = np.arange(-2, 3)
    for _ in range(iterations):
        for oy in range(3):
            for ox in range(3):
                grid = (len(range(oy, h, 3)), len(range(ox, w, 3)))
                nb = _views(np.pad(f, ((0, 0), (2, 2), (2, 2)), mode="edge"), 2, grid, (oy, ox), 3)
                step = _step(nb)
                gb, gy, gx = np.nonzero((_energy(nb, step, alpha) >= t) & (step != 0.0))
                if len(gy) == 0:
                    continue
                s = step[gb, gy, gx]
                y, x = oy + 3 * gy, ox + 3 * gx
                # sum |d_m| over each candidate's 3 x 3 window before and after the update, from its 5 x 5
                # neighbourhood (edges replicated: a border pixel's copies change with it); no other pixel of the
                # subset lies within 2 px.
                rows = np.clip(y[:, None] + window, 0, h - 1)[:, :, None]
                cols = np.clip(x[:, None] + window, 0, w - 1)[:, None, :]
                before = f[gb[:, None, None], rows, cols]
                after = before + s[:, None, None] * ((rows == y[:, None, None]) & (cols == x[:, None, None]))
                inside = (((y[:, None] + window[1:-1]) % h == y[:, None] + window[1:-1])[:, :, None]
                          & ((x[:, None] + window[1:-1]) % w == x[:, None] + window[1:-1])[:, None, :])
                change = [(np.abs(_step(_views(p, 1, (3, 3)))) * inside).sum(axis=(1, 2)) for p in (before, after)]
                keep = change[1] <= change[0]
                f[gb[keep], y[keep], x[keep]] += s[keep]
    return f.reshape(image.shape)
