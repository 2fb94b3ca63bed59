"""On-disk caches of the planning databases (visibility, reachability): written so that a crash
leaves the old file or the new one, read so that a damaged file is noticed and rebuilt.

A cache file is an ``.npz`` holding the arrays and ``_sha256``, a digest of every array's name,
dtype, shape and bytes. :func:`save_arrays` writes it to a temporary file in the same folder,
flushes and fsyncs it, renames it over the final name and fsyncs the folder. :func:`load_arrays`
returns None (and deletes the file) for a file that is empty, truncated, not a zip, has a bad
CRC, lacks an array, or whose digest differs (a flipped byte that the zip format let through):
the caller rebuilds, and a damaged cache never fails a job.
"""
from __future__ import annotations

import hashlib
import os
import tempfile
import zipfile
import zlib
from pathlib import Path
from typing import Callable

import numpy as np

__all__ = ["save_arrays", "load_arrays", "digest"]

_DIGEST = "_sha256"


def digest(arrays: dict[str, np.ndarray]) -> str:
    """sha256 (hex) of the arrays: names, dtypes, shapes and bytes, in name order."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _write_atomic(path: str | Path, fill: Callable) -> Path:
    """``fill(f)`` into a dot-named temporary file beside ``path`` (``.NAME.XXXX.tmp``, which a resume removes after
    a kill), fsync'ed, renamed over ``path``, the folder fsync'ed: atomic and durable."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            fill(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
    return path


def write_bytes_atomic(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically and durably (:func:`_write_atomic`)."""
    return _write_atomic(path, lambda f: f.write(data))


def save_arrays(path: str | Path, arrays: dict[str, np.ndarray], *, compress: bool = False) -> Path:
    """Write ``arrays`` and their digest to ``path`` atomically and durably (fsync of file and folder)."""
    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    save = np.savez_compressed if compress else np.savez
    return _write_atomic(path, lambda f: save(f, **arrays, **{_DIGEST: np.array(digest(arrays))}))


def load_arrays(path: str | Path, names: tuple[str, ...],
                on_damaged: Callable[[str], None] | None = None) -> dict[str, np.ndarray] | None:
    """The arrays ``names`` from the cache file at ``path``, or None when it is missing or damaged.

    A damaged file is deleted (best effort) so that the rebuilt one replaces it; ``on_damaged`` is told
    why (one phrase) first, so that the caller can say that its cache was refused.
    """
    path = Path(path)
    if not path.is_file():
        return None
    try:
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files if k != _DIGEST}
            stored = str(z[_DIGEST])
        missing = [k for k in names if k not in arrays]
        if missing:
            raise KeyError(f"no array {missing[0]!r}")
        if stored != digest(arrays):
            raise ValueError("its digest differs from its arrays")
        return {k: arrays[k] for k in names}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error, NotImplementedError) as exc:
        if on_damaged is not None:
            on_damaged(f"{type(exc).__name__}: {exc}")
        try:
            path.unlink()
        except OSError:
            pass
        return None
