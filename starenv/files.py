"""Files written whole or not at all (and the one reader of the CSV files users hand in, :func:`csv_rows`): a temporary
file beside the target, created exclusively under a unique name (``tempfile.mkstemp``: ``O_EXCL``, so a file or
symbolic link someone prepared there is never opened), flushed and synced, then moved into place with ``os.replace``
(atomic on one file system), removed instead when writing fails.  A reader -- a resumed bench, a dataset build, a
catalogue cache -- never sees half a file.  A symbolic link at the target is refused rather than replaced, and
``replace=False`` keeps an existing target."""

from __future__ import annotations

import csv
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO


@contextmanager
def atomic_file(path: str | os.PathLike, mode: str = "wb", encoding: str | None = None, *,
                replace: bool = True) -> Iterator[IO]:
    """Open a temporary file in ``path``'s folder (created if missing) for writing; on a clean exit it replaces
    ``path``, on an exception it is removed and the exception propagates (an OSError that names no file, such as
    "File too large" or "No space left on device" from a write, is raised again naming ``path``).  A symbolic link
    at ``path`` is a FileExistsError (before anything is written); so is an existing ``path`` when ``replace`` is
    False (checked again, atomically, when the file is moved into place: a hard link that fails if the name
    exists)."""
    path = Path(path)
    _check_target(path, replace)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode, encoding=encoding) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        if replace:
            _check_target(path, replace)
            os.replace(tmp, path)
        else:
            _publish_new(tmp, path)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        if exc.filename is None and exc.errno is not None:  # a write error (full disk, file-size limit) names no file
            raise type(exc)(exc.errno, exc.strerror, str(path)) from exc
        raise
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _check_target(path: Path, replace: bool) -> None:
    if path.is_symlink():
        raise FileExistsError(f"{path}: a symbolic link; refusing to write through or replace it (remove it first)")
    if not replace and path.exists():
        raise FileExistsError(f"{path} exists; refusing to replace it")


def _publish_new(tmp: str, path: Path) -> None:
    """Move ``tmp`` to ``path`` only if nothing is there (a hard link fails if the name exists, even as a link)."""
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise FileExistsError(f"{path} exists; refusing to replace it") from None
    except OSError:  # a file system without hard links: check, then move (a race remains there)
        _check_target(path, replace=False)
        os.replace(tmp, path)
        return
    os.unlink(tmp)


def csv_rows(path: str | os.PathLike, columns: tuple[str, ...], optional: tuple[str, ...] = (), *,
             max_bytes: int) -> Iterator[tuple[int, dict[str, str]]]:
    """The rows of a user's CSV file as (line number, {column: text}), after its header: the first line that is not
    blank or a ``#`` comment, naming every one of ``columns`` and any of ``optional``, each once, in any order (the
    rows' blank and comment lines are skipped too).  A file over ``max_bytes``, not UTF-8, with a wrong header or a
    row of the wrong length raises ValueError naming ``file:line``; one with no header yields nothing."""
    path = Path(path)
    size = path.stat().st_size
    if size > max_bytes:
        raise ValueError(f"{path}: at most {max_bytes} bytes expected, got {size}")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    header: list[str] | None = None
    for line, fields in enumerate(csv.reader(text.splitlines()), start=1):
        if not fields or not "".join(fields).strip() or fields[0].lstrip().startswith("#"):
            continue
        if header is None:
            header = [f.strip() for f in fields]
            if (len(set(header)) != len(header) or not set(columns) <= set(header)
                    or not set(header) <= set(columns) | set(optional)):
                extra = f" (and optionally {', '.join(optional)})" if optional else ""
                raise ValueError(f"{path}:{line}: expected a header naming the columns {', '.join(columns)}{extra}, "
                                 f"each once, got {', '.join(header)[:200]!r}")
            continue
        if len(fields) != len(header):
            raise ValueError(f"{path}:{line}: expected {len(header)} fields ({', '.join(header)}), got {len(fields)}")
        yield line, dict(zip(header, fields, strict=True))
