"""Paper 002's preprocessing of a raw frame into the network's input (numpy; the one implementation the dataset
generator, the identifier agent and the benchmarks share).

The whole frame (DN, H x W) is area-resized to ``size`` x ``size`` (paper: 1024 -> 256): each output pixel is the
mean of its ``H / size`` x ``W / size`` block (the frame's sides must be multiples of ``size``), summed exactly as
integers and divided once.  The background, the lower median of the resized pixels (the middle value, the lower of
the two for an even count: what ``torch.median`` returns), is subtracted.  The network then compresses the result
(``asinh(x / scale_dn)``, :class:`~starenv.agents.identify.network_model.MainStarNet`), an elementwise step that
needs no median on the GPU, where torch has no deterministic one.

With a ``centre`` (x, y px of the frame) the input is shifted by whole blocks so that the block holding that point
lands on block ``(size // 2, size // 2)``; what is shifted in holds zeros (the background).  The paper's network sees
its main star at the input's centre; the identifier puts each detection near the frame's centre there in turn.
"""

from __future__ import annotations

import numpy as np


def lower_median(values: np.ndarray) -> np.ndarray:
    """The lower median of each row of ``values`` (..., n): the ``(n - 1) // 2``-th smallest value."""
    flat = np.asarray(values)
    k = (flat.shape[-1] - 1) // 2
    return np.partition(flat, k, axis=-1)[..., k]


def network_input(frame: np.ndarray, size: int, centre: tuple[float, float] | None = None) -> np.ndarray:
    """The network's input (float32 DN above the background, ``size`` x ``size``) from a raw frame (H, W) or a
    stack of them (B, H, W), shifted to put ``centre`` (x, y px of the frame) at its centre when given; see the
    module docstring."""
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
    image = resized - np.asarray(background, dtype=np.float32)[..., None, None]
    return image if centre is None else recentred(image, (height, width), centre)


def recentred(inputs: np.ndarray, frame_shape: tuple[int, int], centre: tuple[float, float]) -> np.ndarray:
    """Network inputs (..., S, S) of frames of ``frame_shape`` (H, W px) shifted by whole blocks to put the block
    holding ``centre`` (x, y px of the frame) on block (S // 2, S // 2), zeros shifted in."""
    size = inputs.shape[-1]
    col, row = (int(np.floor((float(c) + 0.5) / (n / size))) for c, n in zip(centre, frame_shape[::-1], strict=True))
    return shifted(inputs, size // 2 - row, size // 2 - col)


def shifted(image: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """``image`` (..., H, W) moved by ``rows`` and ``cols`` pixels (down and right), zeros shifted in."""
    out = np.zeros_like(image)
    height, width = image.shape[-2:]
    if abs(rows) >= height or abs(cols) >= width:
        return out
    dst_r, src_r = slice(max(rows, 0), height + min(rows, 0)), slice(max(-rows, 0), height + min(-rows, 0))
    dst_c, src_c = slice(max(cols, 0), width + min(cols, 0)), slice(max(-cols, 0), width + min(-cols, 0))
    out[..., dst_r, dst_c] = image[..., src_r, src_c]
    return out
