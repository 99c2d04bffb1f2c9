"""Paper 002's preprocessing of a raw frame into the network's input (numpy; the one implementation the dataset
generator, the identifier agent and the benchmarks share).

The whole frame (DN, H x W) is area-resized to ``size`` x ``size`` (paper: 1024 -> 256): each output pixel is the
mean of its ``H / size`` x ``W / size`` block (the frame's sides must be multiples of ``size``), summed exactly as
integers and divided once.  The background, the lower median of the resized pixels (the middle value, the lower of
the two for an even count: what ``torch.median`` returns), is subtracted.  The network then compresses the result
(``asinh(x / scale_dn)``, :class:`~starenv.agents.identify.network_model.MainStarNet`), an elementwise step that
needs no median on the GPU, where torch has no deterministic one.
"""

from __future__ import annotations

import numpy as np


def lower_median(values: np.ndarray) -> np.ndarray:
    """The lower median of each row of ``values`` (..., n): the ``(n - 1) // 2``-th smallest value."""
    flat = np.asarray(values)
    k = (flat.shape[-1] - 1) // 2
    return np.partition(flat, k, axis=-1)[..., k]


def network_input(frame: np.ndarray, size: int) -> np.ndarray:
    """The network's input (float32 DN above the background, ``size`` x ``size``) from a raw frame (H, W) or a
    stack of them (B, H, W); see the module docstring."""
    frame = np.asarray(frame)
    height, width = frame.shape[-2:]
    if height % size or width % size:
        raise ValueError(f"network input: a {width} x {height} px frame is not a whole number of {size} x {size} px "
                         f"blocks (its sides must be multiples of the input size)")
    fy, fx = height // size, width // size
    lead = frame.shape[:-2]
    small_ints = frame.dtype.kind in "ub" or frame.dtype in (np.int8, np.int16)
    exact = np.int32 if small_ints and fy * fx <= 1 << 15 else np.int64 if frame.dtype.kind in "iub" else np.float64
    rows = frame[..., 0::fy, :].astype(exact)  # strided adds: several times faster than a reduce over small axes
    for k in range(1, fy):
        rows += frame[..., k::fy, :]
    sums = rows[..., 0::fx].copy()
    for k in range(1, fx):
        sums += rows[..., k::fx]
    resized = (sums / float(fy * fx)).astype(np.float32)
    background = lower_median(resized.reshape(*lead, size * size))
    return resized - np.asarray(background, dtype=np.float32)[..., None, None]
