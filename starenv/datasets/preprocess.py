"""Paper 002's preprocessing of a raw frame into the network's input (numpy; the one implementation the dataset
generator, the identifier agent and the benchmarks share).

The whole frame (DN, H x W) is area-resized by square blocks of ``b = max(H, W) / size`` px (paper: 1024 -> 256,
b = 4): each output pixel is the mean of its b x b block (b must divide both sides), summed exactly as integers and
divided once.  The background, the lower median of the resized pixels (the middle value, the lower of the two for an
even count: what ``torch.median`` returns), is subtracted.  A frame that is not square gives ``H / b`` x ``W / b``
blocks, placed at the centre of the ``size`` x ``size`` input (the short side's rest holds zeros, the background), so
that every input pixel spans the same angle in both directions and a 90 degree turn of the input is a turn of the
sky.  The network then compresses the result
(``asinh(x / scale_dn)``, :class:`~starenv.agents.identify.network_model.MainStarNet`), an elementwise step that
needs no median on the GPU, where torch has no deterministic one.

``background = "local"`` subtracts instead each block's median over the ``LOCAL_BLOCKS`` x ``LOCAL_BLOCKS`` blocks
about it (edges repeated): a real camera's background is not flat (its lens vignettes the sky glow, the glow itself
has a gradient), and a frame's global median leaves that dome in the input, above a faint star's signal.  On a
simulated frame, whose background is flat, both give the same input but for the noise of the estimate.

With a ``centre`` (x, y px of the frame) the input is shifted by whole blocks so that the block holding that point
lands on block ``(size // 2, size // 2)``; what is shifted in holds zeros (the background).  The paper's network sees
its main star at the input's centre; the identifier puts each detection near the frame's centre there in turn.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from starenv import checks

BACKGROUNDS = ("median", "local")
LOCAL_BLOCKS = 5  # the local background's median window (blocks): a star's light falls on at most 4 of its 25


def lower_median(values: np.ndarray) -> np.ndarray:
    """The lower median of each row of ``values`` (..., n): the ``(n - 1) // 2``-th smallest value."""
    flat = np.asarray(values)
    k = (flat.shape[-1] - 1) // 2
    return np.partition(flat, k, axis=-1)[..., k]


def square_block(width: int, height: int, size: int) -> int | None:
    """The side (px) of the square blocks that area-resize a ``width`` x ``height`` px frame to a ``size`` px input
    (``max(width, height) / size``), or None when it is not a whole number of pixels dividing both sides."""
    block, rest = divmod(max(width, height), size)
    return block if block and not rest and width % block == 0 and height % block == 0 else None


def network_input(frame: np.ndarray, size: int, centre: tuple[float, float] | None = None,
                  background: str = "median") -> np.ndarray:
    """The network's input (float32 DN above the background, ``size`` x ``size``) from a raw frame (H, W) or a
    stack of them (B, H, W), shifted to put ``centre`` (x, y px of the frame) at its centre when given;
    ``background``: ``"median"`` or ``"local"`` (see the module docstring)."""
    checks.choice("background", background, BACKGROUNDS)
    frame = np.asarray(frame)
    height, width = frame.shape[-2:]
    block = square_block(width, height, size)
    if block is None:
        raise ValueError(f"network input: a {width} x {height} px frame is not a whole number of square blocks of "
                         f"max({width}, {height}) / {size} px (its longer side must be a multiple of the input size "
                         f"and that block must divide the shorter side)")
    lead = frame.shape[:-2]
    small_ints = frame.dtype.kind in "ub" or frame.dtype in (np.int8, np.int16)
    wide = np.int64 if frame.dtype.kind in "iub" else np.float64
    exact = np.int32 if small_ints and block * block <= 1 << 15 else wide
    rows = frame[..., 0::block, :].astype(exact)  # strided adds: several times faster than a reduce over small axes
    for k in range(1, block):
        rows += frame[..., k::block, :]
    sums = rows[..., 0::block].copy()
    for k in range(1, block):
        sums += rows[..., k::block]
    resized = (sums / float(block * block)).astype(np.float32)
    n_rows, n_cols = resized.shape[-2:]
    if background == "local":
        window = (1,) * len(lead) + (LOCAL_BLOCKS, LOCAL_BLOCKS)
        blocks = resized - ndimage.median_filter(resized, size=window, mode="nearest")
    else:
        level = lower_median(resized.reshape(*lead, n_rows * n_cols))
        blocks = resized - np.asarray(level, dtype=np.float32)[..., None, None]
    top, left = _offset(height // block, width // block, size)
    image = np.zeros((*lead, size, size), dtype=np.float32)
    image[..., top:top + n_rows, left:left + n_cols] = blocks
    return image if centre is None else recentred(image, (height, width), centre)


def _offset(rows: int, cols: int, size: int) -> tuple[int, int]:
    """Where (row, column) a frame's ``rows`` x ``cols`` blocks start in the ``size`` x ``size`` input."""
    return (size - rows) // 2, (size - cols) // 2


def recentred(inputs: np.ndarray, frame_shape: tuple[int, int], centre: tuple[float, float]) -> np.ndarray:
    """Network inputs (..., S, S) of frames of ``frame_shape`` (H, W px) shifted by whole blocks to put the block
    holding ``centre`` (x, y px of the frame) on block (S // 2, S // 2), zeros shifted in."""
    size = inputs.shape[-1]
    height, width = frame_shape
    block = max(height, width) / size
    top, left = _offset(round(height / block), round(width / block), size)
    col, row = (int(np.floor((float(c) + 0.5) / block)) for c in centre)
    return shifted(inputs, size // 2 - row - top, size // 2 - col - left)


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
