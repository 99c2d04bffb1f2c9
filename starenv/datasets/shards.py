"""Datasets on disk: shards of samples, written whole and moved into place, built on local processes or Ray.

``OUT/dataset.json`` holds the spec (scenario inlined), its digest and the project version; ``OUT/shard-NNNNN.npz``
holds samples ``shard * shard_size ...`` stacked per field, plus ``meta`` (JSON as uint8: spec digest, project
version, format version, kind, shard, first index, count).  ``main_star`` shards stack every field; ``centroids``
shards concatenate the per-sample star lists (``xy``, ``catalog_id``, ``magnitude``) and give each sample's
``count`` (offsets are its cumulative sum).  The .npz is written without compression and with fixed zip timestamps,
so the same spec gives bit-identical shard bytes on any executor.  A shard is written under a temporary name and
moved into place (``os.replace``): a killed build leaves complete shards or none, and a new build skips shards
whose meta carries the spec's digest.
"""

from __future__ import annotations

import importlib.metadata
import io
import json
import operator
import os
import sys
import zipfile
from pathlib import Path

import numpy as np

from starenv.datasets.samples import FIELDS, sample
from starenv.datasets.spec import FORMAT_VERSION, DatasetError, DatasetSpec, load_spec
from starenv.files import atomic_file
from starenv.parallel import local_executor, ray_executor

_ZIP_TIME = (1980, 1, 1, 0, 0, 0)


def _version() -> str:
    """The installed project's version (``unknown`` when run from a checkout that was never installed)."""
    try:
        return importlib.metadata.version("starenv")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def shard_path(out: str | Path, shard: int) -> Path:
    return Path(out) / f"shard-{shard:05d}.npz"


def write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """An uncompressed .npz (readable by ``np.load``) with fixed timestamps, written atomically."""
    with atomic_file(path) as f, zipfile.ZipFile(f, "w", compression=zipfile.ZIP_STORED) as zf:
        for name in sorted(arrays):
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.ascontiguousarray(arrays[name]), allow_pickle=False)
            zf.writestr(zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_TIME), buf.getvalue())


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


def build_shard(spec: DatasetSpec, out: str, shard: int) -> int:
    """Generate shard ``shard`` and write it into ``out``; returns its sample count."""
    write_npz(shard_path(out, shard), shard_arrays(spec, shard))
    return len(spec.shard_range(shard))


def read_meta(path: Path) -> dict | None:
    """A shard's meta, or None when the file is missing or unreadable."""
    try:
        with np.load(path) as z:
            return json.loads(bytes(z["meta"]).decode())
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, json.JSONDecodeError):
        return None


def is_complete(spec: DatasetSpec, out: str | Path, shard: int) -> bool:
    meta = read_meta(shard_path(out, shard))
    return meta is not None and meta.get("spec_digest") == spec.digest and meta.get("count") == len(
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
        old = json.loads(manifest.read_text(encoding="utf-8"))
        if old.get("spec_digest") != spec.digest:
            raise DatasetError(f"--out {out}: holds another dataset ({old.get('name')!r}, spec digest "
                               f"{str(old.get('spec_digest'))[:12]}); choose an empty folder")
    else:
        text = json.dumps({"name": spec.name, "kind": spec.kind, "spec_digest": spec.digest,
                           "starenv_version": _version(), "format_version": FORMAT_VERSION, "samples": spec.samples,
                           "n_shards": spec.n_shards, "spec": spec.to_dict()}, sort_keys=True, indent=1, default=list)
        with atomic_file(manifest, "w", encoding="utf-8") as f:
            f.write(text + "\n")
    todo = [s for s in range(spec.n_shards) if not is_complete(spec, out, s)]
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
        for _, count in executor([(spec, str(out), s) for s in todo]):
            bar.update(count)
    finally:
        bar.close()
    return [shard_path(out, s) for s in range(spec.n_shards)]
