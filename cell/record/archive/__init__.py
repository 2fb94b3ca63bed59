"""The archive: job folders (the record of truth) and an index in a database (SQLite or PostgreSQL).

Layout::

    folders.py   Archive: the job folders of one cell (``--archive DIR``), their outbox, sync and verify
    ids.py       job ids are names: resolve_job_id (never leaves the archive), check_archive_root
    records.py   JobRecord: what the index holds of one folder (journal + report.json + manifest hash)
    tables.py    the SQLAlchemy Core tables, declared once (``jobs``, ``targets``)
    index.py     ArchiveIndex: the repository interface (below), shared by the backends
    sqlite.py    SQLiteIndex: embedded, one cell, the default (``sqlite:///DIR/index.sqlite``)
    postgres.py  PostgresIndex: a site of cells on one server (psycopg 3)
    outbox.py    the jobs whose index write waits for the database (or for a person: refused, conflict)
    urls.py      mask_url / scrub: a url or an error as it may be shown (no password)
    push.py      copying a job folder to shared storage (a path, or s3://... through fsspec)
    migrations/  alembic: the schema's history; every open upgrades to the newest revision

Choosing the database: :func:`resolve_url` takes ``--archive-url``, else ``CELL_ARCHIVE_URL``,
else the cell file's ``[archive] url``, else ``sqlite:///<archive DIR>/index.sqlite``;
:func:`open_index` opens it. ``postgresql://user:pw@host:port/db`` (or ``postgres://``).

Reading (the web console and ``cell archive``), with ``ix = open_index(url)``:

* ``ix.list_jobs(part=, part_number=, serial=, verdict=, status=, operator=, since=, until=, cell_id=,
  limit=50, offset=0, newest_first=True) -> list[dict]``: one page of job rows, filters ANDed (equality),
  ``since <= started < until`` (ISO 8601 strings or datetimes). A row: ``id``, ``name``, ``part`` (the
  part's name), ``part_number``, ``serial``, ``cell_id``, ``operator``,
  ``status`` (the state machine's), ``verdict`` (PASS|FAIL|INCOMPLETE|UNTRUSTED|None), ``started``,
  ``finished`` (ISO 8601 UTC strings), ``targets`` (judged targets), ``failed``, ``sigma0_px``,
  ``origin`` (host:folder root of the cell), ``folder`` (the job folder on that cell),
  ``manifest_sha256``, ``problem`` (what of the folder could not be read, or None), ``indexed_at``.
* ``ix.count_jobs(**same filters) -> int``: for paging.
* ``ix.get_job(id) -> dict | None``: one row as above.
* ``ix.job_targets(id) -> list[dict]``: per target ``id``, ``kind``, ``nominal`` (3), ``measured`` (3,
  part frame after alignment), ``cov`` (3x3, m²), ``deviation`` (3), ``deviation_norm_m``,
  ``tolerance_m``, ``uncertainty_U_m``, ``achieved_sigma_m``, ``decision``
  (conforming|nonconforming|inconclusive|None), ``pass``; None where the target was not measured.
* ``ix.target_trend(part, target_id, since=, until=, limit=) -> list[dict]``: oldest first, points
  ``job_id``, ``serial``, ``finished``, ``deviation`` (3), ``deviation_norm_m``, ``tolerance_m``,
  ``uncertainty_U_m``, ``decision``, ``pass``, ``sigma_m`` (achieved sigma). One query on a covering
  index, never a folder scan.
* ``ix.part_summary(part, since=, until=) -> list[dict]``: per target ``id``, ``n``, ``deviation_mean``
  and ``deviation_std`` (3 each), ``norm_mean``, ``norm_std``, ``failed``, ``nonconforming``,
  ``inconclusive``: a part's SPC table in one GROUP BY query.
* ``ix.parts() -> list[str]``, ``ix.part_targets(part) -> list[str]``.
* ``ix.close()``.

A read when the database cannot be reached (or does not answer within the backend's bound) raises
:class:`IndexUnavailable`, one the database refuses :class:`IndexRefused` (both ``CellError``).
A url is shown only through :func:`mask_url` (and free text through :func:`scrub`): never a password.
Times a user filters by (``since``, ``until``) are read by :func:`user_time`: no zone is the cell's local
time, and an ``until`` that is a date is that whole day.

Writing (the job runner, ``cell archive sync``) goes through :class:`Archive`, which keeps the
folder first and the index second: ``Archive(root, url).index_folder(path)`` writes one job in one
transaction, and a job whose write fails because the database is away waits in
``<root>/.outbox/`` until the next write or ``cell archive sync`` drains it (re-indexing is
idempotent: a job is one row, whatever happens). ``Archive.verify_index()`` compares the
database with the folders; :func:`push_job` copies a folder to shared storage and checks the
copy against the manifest.
"""
from __future__ import annotations

import os
from pathlib import Path

from cell.record.archive.folders import Archive
from cell.record.archive.ids import INCOMING, JOB_ID_PATTERN, check_archive_root, check_job_id, resolve_job_id
from cell.record.archive.index import ArchiveIndex, IndexConflict, IndexRefused, IndexUnavailable, user_time
from cell.record.archive.push import push_job
from cell.record.archive.records import JobRecord, job_record
from cell.record.archive.urls import mask_url, scrub

__all__ = ["Archive", "ArchiveIndex", "INCOMING", "JOB_ID_PATTERN", "check_archive_root", "check_job_id",
           "resolve_job_id", "IndexConflict", "IndexRefused", "IndexUnavailable", "JobRecord", "job_record",
           "mask_url", "open_index", "push_job", "resolve_url", "default_url", "scrub", "user_time"]

ENV_URL = "CELL_ARCHIVE_URL"


def default_url(root: Path) -> str:
    """The embedded index of the archive folder ``root``."""
    return f"sqlite:///{Path(root).resolve() / 'index.sqlite'}"


def resolve_url(url: str | None = None, root: Path | None = None, cell_file_url: str | None = None) -> str:
    """The archive database: ``url`` (``--archive-url``), ``$CELL_ARCHIVE_URL``, the cell file's, the default."""
    for u in (url, os.environ.get(ENV_URL), cell_file_url):
        if u:
            return u
    return default_url(Path(root) if root is not None else Path("archive"))


def open_index(url: str) -> ArchiveIndex:
    """The index at ``url``: ``sqlite:///path`` or ``postgresql://...`` (schema upgraded on open)."""
    from calibration.errors import InputError

    if url.startswith("sqlite:///"):
        from cell.record.archive.sqlite import SQLiteIndex

        return SQLiteIndex(Path(url[len("sqlite:///"):]))
    if url.startswith(("postgresql://", "postgresql+psycopg://", "postgres://")):
        from cell.record.archive.postgres import PostgresIndex

        try:
            return PostgresIndex(url)
        except (ValueError, TypeError) as exc:  # a url SQLAlchemy cannot parse (a port that is not a number, ...)
            raise InputError(f"archive url {mask_url(url)!r}: {scrub(exc, url)}") from None
    raise InputError(f"archive url {mask_url(url)!r}: expected sqlite:///PATH or postgresql://USER@HOST:PORT/DB")
