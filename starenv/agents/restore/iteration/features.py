"""The EBPNN's input and target (paper 000, Sec. 3.3 and 4.2).

SUMFC, "the sum of the magnitudes of the Fourier coefficients" of the blur kernel: the paper gives no grid or
normalisation.  We take the kernel normalised to sum 1, zero-padded to ``SUMFC_GRID`` x ``SUMFC_GRID`` and divide the
sum of ``|DFT|`` by the number of coefficients, so SUMFC is 1 for no blur and falls as the blur grows (a mean rather
than a sum: the same ordering, grid-size free).

The optimal iteration count: the Richardson-Lucy iteration, up to a cap, whose estimate has the least mean squared
error against the sharp reference (the highest PSNR).  The paper's automatic iterative RL (Sec. 4.2) stops at the
first rise of that MSE, which can be an early wiggle of the curve: a frame labelled "1" beside neighbours labelled
tens of iterations or more.  The global minimum within the cap is the same optimum where the curve is
unimodal and a stable label where it is not.  The reference is the noise-free
star signal rendered over a vanishing exposure at mid-exposure (what the sensor would see without motion), in DN
above the background, so the MSE weighs every pixel and the noise RL amplifies ends the useful iterations.  (A
centroid-error optimum was the alternative; it is flat over tens of iterations for bright stars and noisy for faint
ones, a poor regression target.)  Long trails converge slowly: their optimum is often the cap itself.
"""

from __future__ import annotations

import numpy as np
from scipy import fft

from starenv import checks
from starenv.agents.restore.algorithms import richardson_lucy

SUMFC_GRID = 256
INITIAL_FLOOR_DN = 0.01  # RL's starting estimate on pixels at or below the background level


def sumfc(kernel: np.ndarray) -> float:
    """SUMFC of a blur kernel (kh, kw) <= ``SUMFC_GRID``: mean ``|DFT|`` of the normalised, zero-padded kernel."""
    k = checks.finite("kernel", kernel)
    if k.ndim != 2 or max(k.shape) > SUMFC_GRID or np.any(k < 0) or k.sum() <= 0:
        raise ValueError(f"kernel must be a non-negative 2-D array with a positive sum, at most {SUMFC_GRID} px a "
                         f"side, got shape {k.shape}")
    spectrum = fft.fft2(k / k.sum(), (SUMFC_GRID, SUMFC_GRID))
    return float(np.abs(spectrum).mean())


def initial_estimate(image: np.ndarray, level: float) -> np.ndarray:
    """Richardson-Lucy's starting estimate: the frame less its background level, floored at ``INITIAL_FLOOR_DN``.
    RL's multiplicative steps scale with signal / (signal + background); from the flat default a star a few DN above
    a 100 DN level takes a hundred iterations just to grow back to its blurred brightness."""
    return np.maximum(np.asarray(image, dtype=np.float64) - level, INITIAL_FLOOR_DN)


def optimal_iterations(image: np.ndarray, kernel: np.ndarray, reference: np.ndarray, background: float,
                       max_iterations: int = 150, mask: np.ndarray | None = None) -> tuple[int, np.ndarray]:
    """The optimal Richardson-Lucy iteration count (module docstring) for ``image`` (DN) and ``kernel``: the
    iteration, started from :func:`initial_estimate` as the deblurrer starts, in
    1 ... ``max_iterations`` of least MSE against ``reference`` (DN above ``background``; the first
    on a tie), over the pixels where ``mask`` is True (default: all).  Returns the count and every iteration's MSE."""
    ref = checks.finite("reference", reference)
    if ref.shape != np.shape(image):
        raise ValueError(f"reference must have the image's shape {np.shape(image)}, got {ref.shape}")
    keep = np.ones(ref.shape, bool) if mask is None else np.asarray(mask, dtype=bool)
    if keep.shape != ref.shape or not keep.any():
        raise ValueError(f"mask must be a boolean array of shape {ref.shape} with at least one True pixel")
    mse: list[float] = []

    def watch(k: int, estimate: np.ndarray) -> bool:
        mse.append(float(np.mean((estimate[keep] - ref[keep]) ** 2)))
        return False

    richardson_lucy(image, kernel, checks.integer("max_iterations", max_iterations, 1, 100000),
                    background=background, initial=initial_estimate(image, background), callback=watch)
    return int(np.argmin(mse)) + 1, np.array(mse)
