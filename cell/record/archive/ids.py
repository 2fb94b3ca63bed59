"""Job ids are names, never paths: :func:`resolve_job_id` is the one way from an id (given on the
command line or to the web console) to a job folder, and it never leaves the archive. A job still
being set up (before ACQUIRE) lives in ``.incoming/``; it is found there too.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

from calibration.errors import InputError
from cell.record.jobfolder import JobFolder

#: what a job id may be made of: letters, digits, '-', '_', '.', '+', ':' (not first: '.'); no separators
JOB_ID_PATTERN = re.compile(r"[A-Za-z0-9_+:-][A-Za-z0-9_.+:-]{0,199}")
INCOMING = ".incoming"


def check_job_id(job_id: str) -> str:
    """``job_id`` if it is a plain name (no path separator, no '..', no leading '.'); else ``InputError``."""
    if not isinstance(job_id, str) or not JOB_ID_PATTERN.fullmatch(job_id) or job_id in (".", ".."):
        shown = job_id if isinstance(job_id, str) and len(job_id) < 80 else f"{str(job_id)[:80]}..."
        raise InputError(f"{shown!r} is not a job id: an id is a name of letters, digits, '-', '_', '.', '+', ':' "
                         "(no path, no '..'); see 'cell archive list'")
    return job_id


def resolve_job_id(root: Path, job_id: str) -> JobFolder:
    """The folder of job ``job_id`` in the archive at ``root`` (finished, or staged in ``.incoming``).

    The id is a name, never a path; a folder that is a symlink leading out of the archive is
    refused. Used by every command that takes a job id, and by the web console.

    Raises:
        InputError: not a job id, no such job, or a folder that leaves the archive.
    """
    check_job_id(job_id)
    root = Path(root)
    real_root = root.resolve()
    for parent in (root, root / INCOMING):
        p = parent / job_id
        if not (p.is_dir() or p.is_symlink()):
            continue
        real = p.resolve()
        if real.parent != parent.resolve() or not real.is_relative_to(real_root) or not real.is_dir():
            raise InputError(f"{root}: job {job_id!r} is a link that leads out of the archive ({real}); refused")
        return JobFolder(p)
    raise InputError(f"{root}: no job {job_id!r} in the archive (see 'cell archive list')")


def check_archive_root(root: Path, *, write: bool) -> Path:
    """The archive folder, checked: not a file; writable when ``write``. ``InputError`` otherwise."""
    root = Path(root)
    if root.exists() and not root.is_dir():
        raise InputError(f"--archive {root}: is a file, not an archive folder")
    if write:
        try:
            root.mkdir(parents=True, exist_ok=True)
            probe = root / f".write-probe-{os.getpid()}"
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as exc:
            raise InputError(f"--archive {root}: cannot write there ({exc.strerror or exc}); choose a writable "
                             "folder") from None
    return root
