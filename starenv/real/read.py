"""Real frames in: one grey image from a FITS, PNG or TIFF file, as the detector takes it.

``read_frame(path)`` returns a 2-D array (rows x columns, DN as stored): PNG and TIFF of 8 or 16 bits per pixel
(OpenCV), FITS images of integer or floating-point data (astropy, the first HDU holding a 2-D image; unsigned 16-bit
stored with ``BZERO = 32768`` comes back as uint16).  A colour file whose channels are all equal (a grey frame saved
as RGB or RGBA, opaque) is read as its one channel; a true colour one is refused.  Every refusal is one
:class:`FrameFileError` line naming the file: unreadable, not an image, another depth, colour, empty, or larger than
``MAX_FRAME_PIXELS`` (the largest frame a scenario may simulate, checked from the file's header before the pixels are
decoded where the format allows).
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np

from starenv.scenario import MAX_FRAME_PIXELS

MAX_FILE_BYTES = 2**30  # no frame file is read beyond this size
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
TIFF_SIGNATURES = (b"II*\x00", b"MM\x00*")
FITS_SIGNATURE = b"SIMPLE  ="
SUFFIXES = {".fits": "fits", ".fit": "fits", ".fts": "fits", ".png": "png", ".tif": "tiff", ".tiff": "tiff"}
TIFF_WIDTH_TAG, TIFF_LENGTH_TAG = 256, 257


class FrameFileError(ValueError):
    """A frame file that cannot be read as one grey image; the message names the file."""


def read_frame(path: str | os.PathLike) -> np.ndarray:
    """The grey image (rows, columns) stored in ``path``: uint8 or uint16 for PNG and TIFF, the stored type for FITS
    (see the module docstring)."""
    path = Path(path)
    fail = _failure(path)
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(2880)
    except OSError as exc:
        raise fail(f"cannot be read ({exc.strerror or exc})") from exc
    if size == 0:
        raise fail("is empty (0 bytes)")
    if size > MAX_FILE_BYTES:
        raise fail(f"is {size} bytes: larger than the {MAX_FILE_BYTES} a frame file may be")
    kind = _kind(head)
    if kind is None:
        expected = SUFFIXES.get(path.suffix.lower())
        what = f"not a valid {expected.upper()} file" if expected else "not a FITS, PNG or TIFF image"
        raise fail(f"is {what} (unrecognised content)")
    image = _read_fits(path, fail) if kind == "fits" else _read_opencv(path, head, kind, fail)
    return _grey(image, fail)


def _failure(path: Path):
    def fail(why: str) -> FrameFileError:
        return FrameFileError(f"{path}: {why}")

    return fail


def _kind(head: bytes) -> str | None:
    """The file's format from its first bytes."""
    if head.startswith(PNG_SIGNATURE):
        return "png"
    if head[:4] in TIFF_SIGNATURES:
        return "tiff"
    if head.startswith(FITS_SIGNATURE):
        return "fits"
    return None


def _check_pixels(width: int, height: int, fail) -> None:
    if width * height > MAX_FRAME_PIXELS:
        raise fail(f"is {width} x {height} px: more than the {MAX_FRAME_PIXELS} pixels a frame may hold")
    if width * height == 0:
        raise fail(f"is empty ({width} x {height} px)")


def _declared_size(path: Path, head: bytes, kind: str) -> tuple[int, int] | None:
    """Width and height the file's header declares (PNG's IHDR, TIFF's first directory), or None if unreadable."""
    if kind == "png":
        if len(head) < 24 or head[12:16] != b"IHDR":
            return None
        return struct.unpack(">II", head[16:24])
    order = "<" if head[:2] == b"II" else ">"
    try:
        with open(path, "rb") as f:
            (offset,) = struct.unpack(order + "I", head[4:8])
            f.seek(offset)
            (count,) = struct.unpack(order + "H", f.read(2))
            entries = f.read(12 * min(count, 4096))
    except (OSError, struct.error):
        return None
    found = {}
    for k in range(len(entries) // 12):
        tag, kind_code, _ = struct.unpack(order + "HHI", entries[12 * k: 12 * k + 8])
        if tag in (TIFF_WIDTH_TAG, TIFF_LENGTH_TAG):
            fmt = order + ("H" if kind_code == 3 else "I")
            found[tag] = struct.unpack(fmt, entries[12 * k + 8: 12 * k + 8 + struct.calcsize(fmt)])[0]
    if len(found) < 2:
        return None
    return found[TIFF_WIDTH_TAG], found[TIFF_LENGTH_TAG]


def _read_opencv(path: Path, head: bytes, kind: str, fail) -> np.ndarray:
    import cv2

    declared = _declared_size(path, head, kind)
    if declared is None:
        raise fail(f"is not a valid {kind.upper()} file (no image size in its header)")
    _check_pixels(*declared, fail)
    try:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise fail(f"cannot be decoded as {kind.upper()} ({str(exc).strip().splitlines()[-1]})") from exc
    if image is None:
        raise fail(f"cannot be decoded as {kind.upper()} (damaged or an unsupported variant)")
    if image.dtype not in (np.uint8, np.uint16):
        raise fail(f"holds {image.dtype} pixels: expected 8- or 16-bit integers")
    if image.ndim == 3 and image.shape[2] >= 3:  # OpenCV's BGR(A): reorder is irrelevant, only equality matters
        image = image[..., :3] if image.shape[2] == 3 else _opaque(image, fail)
    return image


def _opaque(image: np.ndarray, fail) -> np.ndarray:
    """The colour channels of a BGRA image whose alpha is fully opaque."""
    if not np.all(image[..., 3] == np.iinfo(image.dtype).max):
        raise fail("has a transparent alpha channel: expected a grey frame")
    return image[..., :3]


def _read_fits(path: Path, fail) -> np.ndarray:
    try:
        from astropy.io import fits
    except ModuleNotFoundError as exc:
        raise ModuleNotFoundError('reading FITS frames needs astropy: pip install "starenv[fits]"') from exc
    try:
        with fits.open(path, memmap=False, lazy_load_hdus=True) as hdus:
            for hdu in hdus:
                naxis = int(hdu.header.get("NAXIS", 0))
                if naxis == 0 or not getattr(hdu, "is_image", False):
                    continue
                shape = [int(hdu.header.get(f"NAXIS{k}", 0)) for k in range(1, naxis + 1)]
                if naxis > 2 and any(n > 1 for n in shape[2:]):
                    raise fail(f"holds a {' x '.join(map(str, shape))} image cube: expected one grey frame")
                _check_pixels(shape[0], shape[1] if naxis > 1 else 1, fail)
                data = np.asarray(hdu.data).reshape(shape[1] if naxis > 1 else 1, shape[0])
                return data if data.dtype.isnative else data.astype(data.dtype.newbyteorder("="))
    except FrameFileError:
        raise
    except (OSError, ValueError, TypeError, IndexError) as exc:
        raise fail(f"cannot be read as FITS ({str(exc).strip().splitlines()[0] if str(exc) else type(exc).__name__})")\
            from exc
    raise fail("holds no image (no HDU with pixel data)")


def _grey(image: np.ndarray, fail) -> np.ndarray:
    """One grey channel: a 2-D image as it is, a colour one only when its channels are equal."""
    if image.ndim == 3:
        if not all(np.array_equal(image[..., 0], image[..., c]) for c in range(1, image.shape[2])):
            raise fail(f"is a colour image ({image.shape[2]} channels that differ): convert it to one grey channel "
                       "(e.g. cv2.cvtColor(..., cv2.COLOR_BGR2GRAY)) first")
        image = image[..., 0]
    if image.ndim != 2 or image.size == 0:
        raise fail(f"is empty or not a 2-D image (shape {image.shape})")
    if np.issubdtype(image.dtype, np.floating):
        if not np.all(np.isfinite(image)):
            raise fail("holds NaN or infinite pixels")
    elif not np.issubdtype(image.dtype, np.integer) or (
            image.dtype.itemsize > 2 and (image.min() < -(2**15) or image.max() >= 2**16)):
        raise fail(f"holds {image.dtype} pixels outside 16 bits: expected 8- or 16-bit counts")
    return np.ascontiguousarray(image)
