"""Datasets on disk: shards of samples, written whole and moved into place, built on local processes or Ray.

``OUT/dataset.json`` holds the spec (scenario inlined), its digest and the project version; ``OUT/shard-NNNNN.npz``
holds samples ``shard * shard_size ...`` stacked per field, plus ``meta`` (JSON as uint8: spec digest, project
version, format version, kind, shard, first index, count).  ``main_star`` shards stack every field; ``centroids``
shards concatenate the per-sample star lists (``xy``, ``catalog_id``, ``magnitude``) and give each sample's
``count`` (offsets are its cumulative sum).  The .npz is written without compression and with fixed zip timestamps,
so the same spec gives bit-identical shard bytes on any executor.  A shard is written under a temporary name and
moved into place (``os.replace``): a killed build leaves complete shards or none.  ``OUT/shards.json`` records each
finished shard's SHA-256 (written by the process that drives the build, after the shard is in place): a new build
reuses only shards whose bytes have the recorded hash (any other file, or one killed before its hash was recorded,
is built again: the same bytes), and :class:`~starenv.agents.identify.network_data.ShardDataset` refuses a shard
whose bytes do not.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import io
import json
import math
import operator
import os
import struct
import sys
import zipfile
from pathlib import Path

import numpy as np

from starenv.datasets.samples import FIELDS, sample
from starenv.datasets.spec import FORMAT_VERSION, DatasetError, DatasetSpec, load_spec
from starenv.files import atomic_file
from starenv.parallel import local_executor, ray_executor

_ZIP_TIME = (1980, 1, 1, 0, 0, 0)
INDEX = "shards.json"  # {"spec_digest": ..., "sha256": {shard file name: SHA-256 of its bytes}}
MAX_INDEX_BYTES = 1 << 26  # a name and a 64-digit hash per shard: far more shards than any spec asks for
_LOCAL_HEADER = struct.Struct("<4s5H3L2H")  # a zip member's local file header, up to its name (APPNOTE 4.3.7)
_NPY_HEADER_MAX = 1 << 16  # bytes read for an .npy header: numpy refuses headers over 10 000 bytes


def _version() -> str:
    """The installed project's version (``unknown`` when run from a checkout that was never installed)."""
    try:
        return importlib.metadata.version("starenv")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def shard_path(out: str | Path, shard: int) -> Path:
    """The file of shard number ``shard`` in the dataset folder ``out``."""
    return Path(out) / f"shard-{shard:05d}.npz"


def write_npz(path: Path, arrays: dict[str, np.ndarray]) -> str:
    """An uncompressed .npz (readable by ``np.load``) with fixed timestamps, written atomically; its SHA-256."""
    data = io.BytesIO()
    with zipfile.ZipFile(data, "w", compression=zipfile.ZIP_STORED) as zf:
        for name in sorted(arrays):
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.ascontiguousarray(arrays[name]), allow_pickle=False)
            zf.writestr(zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_TIME), buf.getvalue())
    with atomic_file(path) as f:
        f.write(data.getvalue())
    return hashlib.sha256(data.getvalue()).hexdigest()


class _ViewFile(io.RawIOBase):
    """A read-only, seekable file over a buffer, without the copy ``io.BytesIO`` makes (for the zip directory)."""

    def __init__(self, view: memoryview):
        super().__init__()
        self.view, self.pos = view, 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self.pos

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self.pos, io.SEEK_END: len(self.view)}[whence]
        if base + offset < 0:
            raise OSError("seek before the start")
        self.pos = base + offset
        return self.pos

    def readinto(self, buffer) -> int:
        chunk = self.view[self.pos:self.pos + len(buffer)]
        buffer[:len(chunk)] = chunk
        self.pos += len(chunk)
        return len(chunk)


def read_arrays(data: bytes | bytearray, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The arrays ``names`` of the .npz bytes ``data`` (as :func:`write_npz` writes them), each a view into ``data``
    (no copy; writable when ``data`` is a bytearray).  Each member's headers are checked before any view is made:
    stored uncompressed, inside ``data``, a plain numeric dtype in C order, and exactly the bytes its shape needs.
    Anything else is a ValueError.  Integrity is the caller's SHA-256 check, not the zip's CRC."""
    out = {}
    view = memoryview(data)
    try:
        with zipfile.ZipFile(io.BufferedReader(_ViewFile(view))) as zf:
            for name in names:
                info = zf.getinfo(f"{name}.npy")
                local = info.header_offset
                fixed = bytes(view[local:local + _LOCAL_HEADER.size])
                if (info.compress_type != zipfile.ZIP_STORED or info.compress_size != info.file_size
                        or len(fixed) != _LOCAL_HEADER.size or fixed[:4] != b"PK\x03\x04"):
                    raise ValueError(f"{name}: not stored as write_npz stores it")
                name_len, extra_len = _LOCAL_HEADER.unpack(fixed)[-2:]
                start = local + _LOCAL_HEADER.size + name_len + extra_len
                if start + info.file_size > len(data):
                    raise ValueError(f"{name}: {info.file_size} bytes from offset {start} run past the file")
                head = io.BytesIO(bytes(view[start:start + min(info.file_size, _NPY_HEADER_MAX)]))
                version = np.lib.format.read_magic(head)
                read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else \
                    np.lib.format.read_array_header_2_0
                shape, fortran, dtype = read_header(head)
                body = info.file_size - head.tell()
                if dtype.kind not in "biuf" or fortran or math.prod(shape) * dtype.itemsize != body:
                    raise ValueError(f"{name}: a header of {shape} {dtype} for {body} bytes")
                out[name] = np.frombuffer(view, dtype, math.prod(shape), start + head.tell()).reshape(shape)
    except (KeyError, OSError, EOFError, zipfile.BadZipFile, RuntimeError, NotImplementedError, struct.error) as exc:
        raise ValueError(f"not a shard as write_npz writes it ({type(exc).__name__}: {exc})") from exc
    return out


def read_index(out: str | Path, spec_digest: str) -> dict[str, str]:
    """The recorded SHA-256 of each finished shard of ``out`` (file name -> hex); empty when there is no index.  An
    index that cannot be read or is of another spec is a ValueError naming it."""
    path = Path(out) / INDEX
    if not path.is_file():
        return {}
    try:
        if path.stat().st_size > MAX_INDEX_BYTES:
            raise ValueError(f"larger than {MAX_INDEX_BYTES} bytes")
        index = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as exc:
        raise DatasetError(f"{path}: not a readable shard index ({exc})") from exc
    hashes = index.get("sha256") if isinstance(index, dict) else None
    if (not isinstance(hashes, dict) or index.get("spec_digest") != spec_digest
            or not all(isinstance(k, str) and isinstance(v, str) and len(v) == 64 for k, v in hashes.items())):
        raise DatasetError(f"{path}: not the shard index of spec {spec_digest[:12]}")
    return hashes


def record_shards(out: str | Path, spec_digest: str, hashes: dict[str, str]) -> None:
    """Write ``out``'s shard index (atomically): ``hashes`` maps shard file names to their SHA-256."""
    text = json.dumps({"spec_digest": spec_digest, "sha256": dict(sorted(hashes.items()))}, indent=1)
    with atomic_file(Path(out) / INDEX, "w", encoding="utf-8") as f:
        f.write(text + "\n")


def shard_arrays(spec: DatasetSpec, shard: int) -> dict[str, np.ndarray]:
    """The arrays of shard ``shard`` (its samples generated in this process)."""
    indices = spec.shard_range(shard)
    samples = [sample(spec, i) for i in indices]
    per_star, per_sample = FIELDS[spec.kind]
    arrays = {k: np.concatenate([s[k] for s in samples]) for k in per_star}  # sample j's rows: its ``count``
    arrays.update({k: np.stack([s[k] for s in samples]) for k in per_sample})
    arrays["index"] = np.arange(indices.start, indices.stop, dtype=np.int64)
    meta = {"spec_digest": spec.digest, "starenv_version": _version(), "format_version": FORMAT_VERSION,
            "kind": spec.kind, "name": spec.name, "shard": shard, "first_index": indices.start,
            "count": len(indices)}
    arrays["meta"] = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), dtype=np.uint8)
    return arrays


def build_shard(spec: DatasetSpec, out: str, shard: int) -> tuple[int, str]:
    """Generate shard ``shard`` and write it into ``out``; returns its sample count and the SHA-256 of its bytes."""
    sha = write_npz(shard_path(out, shard), shard_arrays(spec, shard))
    return len(spec.shard_range(shard)), sha


def read_meta(path: Path) -> dict | None:
    """A shard's meta, or None when the file is missing or unreadable."""
    try:
        return json.loads(read_arrays(Path(path).read_bytes(), ("meta",))["meta"].tobytes().decode())
    except (OSError, ValueError, RecursionError):
        return None


def is_complete(spec: DatasetSpec, out: str | Path, shard: int, index: dict[str, str]) -> bool:
    """Whether shard ``shard`` of ``out`` is finished: its bytes have the SHA-256 ``index`` records for it, and its
    meta names the spec and the shard's sample count."""
    path = shard_path(out, shard)
    recorded = index.get(path.name)
    try:
        if recorded is None or hashlib.sha256(path.read_bytes()).hexdigest() != recorded:
            return False
    except OSError:
        return False
    meta = read_meta(path)
    return isinstance(meta, dict) and meta.get("spec_digest") == spec.digest and meta.get("count") == len(
        spec.shard_range(shard))


def build_dataset(spec: DatasetSpec | str | Path, out: str | Path, jobs: int | None = None, use_ray: bool = False,
                  ray_address: str | None = None, ray_options: dict | None = None, progress: bool = True,
                  log=print) -> list[Path]:
    """Write every shard of ``spec`` not already complete in ``out``; return all shard paths in order.

    ``jobs``: local worker processes (default: the CPU count; 1 builds in this process).  ``use_ray``: build on the
    Ray cluster at ``ray_address`` (None: a local instance; ``OUT`` must be a folder every node shares).
    """
    from tqdm import tqdm

    spec = spec if isinstance(spec, DatasetSpec) else load_spec(spec)
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DatasetError(f"--out {out}: expected a folder that can be created and written ({exc})") from exc
    manifest = out / "dataset.json"
    if manifest.is_file():
        try:
            old = json.loads(manifest.read_text(encoding="utf-8"))
        except (OSError, ValueError, RecursionError) as exc:
            raise DatasetError(f"{manifest}: not readable ({exc}); choose an empty folder") from exc
        if not isinstance(old, dict) or old.get("spec_digest") != spec.digest:
            old = old if isinstance(old, dict) else {}
            raise DatasetError(f"--out {out}: holds another dataset ({old.get('name')!r}, spec digest "
                               f"{str(old.get('spec_digest'))[:12]}); choose an empty folder")
    else:
        text = json.dumps({"name": spec.name, "kind": spec.kind, "spec_digest": spec.digest,
                           "starenv_version": _version(), "format_version": FORMAT_VERSION, "samples": spec.samples,
                           "n_shards": spec.n_shards, "spec": spec.to_dict()}, sort_keys=True, indent=1, default=list)
        with atomic_file(manifest, "w", encoding="utf-8") as f:
            f.write(text + "\n")
    try:
        index = read_index(out, spec.digest)
    except DatasetError as exc:
        log(f"rebuilding every shard: {exc}")
        index = {}
    todo = [s for s in range(spec.n_shards) if not is_complete(spec, out, s, index)]
    index = {shard_path(out, s).name: index[shard_path(out, s).name] for s in range(spec.n_shards) if s not in todo}
    reused = spec.n_shards - len(todo)
    if reused:
        log(f"reusing {reused} complete shard(s) in {out}")
    key = operator.itemgetter(2)
    jobs = (os.cpu_count() or 1) if jobs is None else jobs
    if use_ray:
        executor = ray_executor(build_shard, key, ray_address, ray_options, DatasetError)
    else:
        executor = local_executor(build_shard, key, jobs)
    done = spec.samples - sum(len(spec.shard_range(s)) for s in todo)
    bar = tqdm(total=spec.samples, initial=done, unit="sample", disable=not progress, file=sys.stderr,
               desc=spec.name)
    try:
        for shard, (count, sha) in executor([(spec, str(out), s) for s in todo]):
            index[shard_path(out, shard).name] = sha
            record_shards(out, spec.digest, index)  # after the shard is in place: a kill before leaves it unrecorded
            bar.update(count)
    finally:
        bar.close()
    return [shard_path(out, s) for s in range(spec.n_shards)]
