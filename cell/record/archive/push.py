"""Pushing a closed job folder to the site's shared storage, checked against its manifest.

``dest`` is a folder path or any fsspec URL (``s3://bucket/prefix`` with s3fs installed; its
endpoint and keys come from the usual AWS variables or ``storage_options``). The job lands in
``<dest>/<job_id>/``: every file of the manifest first, ``manifest.json`` last (a reader that sees
the manifest sees a whole job), then every file is read back from the storage and its sha256
compared with the manifest. A folder that does not match its own manifest is not pushed.
"""
from __future__ import annotations

import hashlib
import json
import posixpath
from pathlib import Path

from calibration.errors import CellError, InputError
from cell.record.jobfolder import MANIFEST, JobFolder


class PushError(CellError):
    """The copy on shared storage differs from the manifest (or the storage failed)."""


def _fs(dest: str, storage_options: dict | None):
    import fsspec

    try:
        return fsspec.core.url_to_fs(str(dest), **(storage_options or {}))
    except ImportError as exc:  # e.g. s3:// without s3fs
        raise InputError(f"{dest}: cannot open this storage ({exc}); install the cell with its [s3] extra") from None


def _sha256_remote(fs, path: str) -> str:
    h = hashlib.sha256()
    with fs.open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def push_job(folder: Path, dest: str, *, storage_options: dict | None = None) -> dict:
    """Copy the job folder to ``dest``/<job_id> and verify the copy; returns what was pushed.

    Raises ``InputError`` if the folder is not closed or not intact, ``PushError`` if the copy
    cannot be written or does not read back as the manifest says.
    """
    jf = JobFolder(Path(folder))
    problems = jf.verify_manifest()
    if problems:
        raise InputError(f"{jf.job_id}: not pushed, the folder does not match its manifest: {'; '.join(problems[:5])}")
    manifest = json.loads(jf.file(MANIFEST).read_text())
    fs, root = _fs(dest, storage_options)
    base = posixpath.join(root.rstrip("/"), jf.job_id)
    names = sorted(manifest["files"])
    try:
        fs.makedirs(base, exist_ok=True)
        for name in [*names, MANIFEST]:
            remote = posixpath.join(base, name)
            parent = posixpath.dirname(remote)
            if parent != base:
                fs.makedirs(parent, exist_ok=True)
            fs.put_file(str(jf.file(name)), remote)
    except OSError as exc:
        raise PushError(f"{jf.job_id}: push to {dest} failed: {exc}") from exc
    # read back: every file, and the manifest itself
    bad = []
    try:
        for name in names:
            got = _sha256_remote(fs, posixpath.join(base, name))
            if got != manifest["files"][name]["sha256"]:
                bad.append(name)
        remote_manifest = json.loads(fs.cat_file(posixpath.join(base, MANIFEST)))
    except (OSError, ValueError) as exc:
        raise PushError(f"{jf.job_id}: cannot read back the copy at {dest}: {exc}") from exc
    if remote_manifest != manifest:
        bad.append(MANIFEST)
    if bad:
        raise PushError(f"{jf.job_id}: the copy at {dest} differs from the manifest: {', '.join(bad[:10])}")
    nbytes = sum(m["bytes"] for m in manifest["files"].values())
    return {"job_id": jf.job_id, "dest": f"{str(dest).rstrip('/')}/{jf.job_id}", "files": len(names) + 1,
            "bytes": nbytes, "verified": True}
