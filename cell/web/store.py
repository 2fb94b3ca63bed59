"""What the console reads from the archive, behind one small adapter.

Lists, trends and a part's targets are queries of the archive's index (SQLite or PostgreSQL:
:func:`cell.record.archive.open_index`, issue 19); a job's journal, audit trail and report.json are
read from its folder (the index does not hold them).

Every job id that comes from a URL goes through :func:`job_folder`, which refuses anything that
is not a plain folder name directly inside the archive.
"""
from __future__ import annotations

import json
import re
from datetime import datetime, timedelta, timezone
from pathlib import Path

from calibration.errors import InputError
from cell.record.archive import Archive, IndexUnavailable
from cell.record.decisions import beyond, exclusion, measured, trusted, undecided
from cell.record.jobfolder import JobFolder
from cell.record.runinfo import read_run_info

_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.:-]{0,150}$")


class NotFound(InputError):
    """No such job (or an id that could not name one): the console answers 404."""


def job_folder(root: Path, job_id: str, *, staged: bool = False) -> Path:
    """The folder of job ``job_id`` in archive ``root``; NotFound for anything else.

    Goes through the archive's own resolver (:func:`cell.record.archive.resolve_job_id`: a plain name,
    no separators, no '..', no leading dot, no link out of the archive); a job still staged in
    ``.incoming`` counts only with ``staged``. Every id that comes from a URL passes here.
    """
    from cell.record.archive import resolve_job_id

    if not isinstance(job_id, str) or not _ID.match(job_id) or ".." in job_id:
        raise NotFound(f"no job {str(job_id)[:60]!r}")
    try:
        p = resolve_job_id(Path(root), job_id).path
    except InputError:
        raise NotFound(f"no job {job_id!r}") from None
    root = Path(root).resolve()
    real = p.resolve()
    if not (real.parent == root or (staged and real.parent == root / ".incoming")) or \
            not (real / "journal.jsonl").is_file():
        raise NotFound(f"no job {job_id!r}")
    return real


def _parse_time(s: str | None) -> datetime | None:
    if not s:
        return None
    try:
        d = datetime.fromisoformat(s)
    except ValueError:
        raise InputError(f"date {s!r}: use YYYY-MM-DD or an ISO 8601 time") from None
    return d if d.tzinfo is not None else d.astimezone()


def _utc_ms(t: str | None) -> str | None:
    """An index time as ISO 8601 UTC with milliseconds (the backends' trend queries format it differently)."""
    if not t:
        return None
    return datetime.fromisoformat(t).astimezone(timezone.utc).isoformat(timespec="milliseconds")


class ArchiveView:
    """Read-only questions the console asks of the archive at ``root``, whose index is at ``url``.

    ``url``: ``sqlite:///PATH`` or ``postgresql://...`` (None: ``CELL_ARCHIVE_URL``, else the SQLite
    index in the archive folder). Lists and trends are queries of the index (one open index per view:
    :meth:`close` it); a job's journal, audit and report are read from its folder.
    """

    #: rows fetched per query while filtering serials by substring (the index matches serials exactly)
    PAGE = 500

    def __init__(self, root: Path, url: str | None = None):
        from cell.record.archive import resolve_url

        self.root = Path(root).resolve()
        self.url = resolve_url(url, self.root)
        self.archive = Archive(self.root, self.url)

    @property
    def index(self):
        """The open index (one per view; ``IndexUnavailable`` while the database cannot be reached)."""
        return self.archive.index

    def close(self) -> None:
        self.archive.close()

    def refresh(self, job_id: str | None = None) -> None:
        """Bring the index up to date with the folders (one job, or all)."""
        if job_id is None:
            self.archive.reindex()
        else:
            self.archive.reindex(only=job_folder(self.root, job_id))

    def _drain(self) -> None:
        try:
            self.archive.drain()  # jobs whose index write waited for the database
        except IndexUnavailable:
            pass

    def _rows(self, part: str | None, limit: int | None, offset: int = 0, **filters) -> list[dict]:
        """Index rows, newest first; ``part`` matches the part number or the part's name (two queries, merged)."""
        ix = self.index
        if not part:
            return ix.list_jobs(limit=limit, offset=offset, **filters)
        n = None if limit is None else limit + offset
        rows = {r["id"]: r for r in ix.list_jobs(part_number=part, limit=n, **filters)}
        rows |= {r["id"]: r for r in ix.list_jobs(part=part, limit=n, **filters)}
        out = sorted(rows.values(), key=lambda r: (r.get("started") or "", r["id"]), reverse=True)
        return out[offset:] if limit is None else out[offset:offset + limit]

    def list_jobs(self, part: str | None = None, serial: str | None = None, verdict: str | None = None,
                  operator: str | None = None, since: str | None = None, until: str | None = None,
                  status: str | None = None, limit: int = 500) -> list[dict]:
        """Jobs, newest first, filtered. ``part`` matches the part number or the part's name; ``serial`` a
        substring (any case); ``since``/``until`` the start time (both inclusive; a date is the whole day)."""
        t0, t1 = _parse_time(since), _parse_time(until)
        if t1 is not None:
            # the index's until is exclusive: the next day of a date, else the next microsecond
            t1 += timedelta(days=1) if len(until or "") == 10 else timedelta(microseconds=1)
        filters = {"verdict": verdict.upper() if verdict else None, "status": status.upper() if status else None,
                   "operator": operator or None, "since": t0, "until": t1}
        filters = {k: v for k, v in filters.items() if v is not None}
        self._drain()
        if not serial:
            rows = self._rows(part, limit, **filters)
        else:  # a substring: filtered here, page by page, until ``limit`` rows match
            rows, offset, s = [], 0, serial.lower()
            while len(rows) < limit:
                page = self._rows(part, self.PAGE, offset, **filters)
                rows += [r for r in page if s in (r.get("serial") or "").lower()]
                if len(page) < self.PAGE:
                    break
                offset += self.PAGE
            rows = rows[:limit]
        # failed (the index's count) is measured and beyond tolerance; the targets not measured are counted apart
        missing = self.index.not_measured_counts([r["id"] for r in rows if r.get("targets") is not None])
        for r in rows:
            r.pop("folder", None)
            r["not_measured"] = missing.get(r["id"], 0) if r.get("targets") is not None else None
        return rows

    def report(self, job_id: str) -> dict | None:
        p = job_folder(self.root, job_id) / "report.json"
        return json.loads(p.read_text()) if p.exists() else None

    def get_job(self, job_id: str) -> dict:
        """One job: its index row, who/what (run.json), its journal's terminal record, its report summary."""
        folder = job_folder(self.root, job_id)
        recs, damage = JobFolder(folder).read_journal()
        state = next((r["to"] for r in reversed(recs) if r["event"] == "state"), "CREATED")
        terminal = next((r for r in reversed(recs) if r["event"] == "terminal"), None)
        info = read_run_info(folder)
        doc = {"id": job_id, "state": state, "part": info["part"], "operator": info["operator"],
               "cell_id": info["cell_id"], "started": recs[0]["t"] if recs else None,
               "reason": terminal.get("reason") if terminal else "", "verdict": None,
               "audit": [r for r in recs if r.get("event") in ("audit", "created", "resumed")],
               "record_damage": None if damage is None else str(damage)}
        rep = self.report(job_id)
        if rep is not None:
            doc |= {"verdict": rep.get("verdict"), "name": rep["job"].get("name"), "part_name": rep["job"].get("part"),
                    "finished": rep["job"].get("finished"), "targets": len(rep["targets"]),
                    "failed": [t["id"] for t in rep["targets"] if beyond(t)],  # measured and beyond tolerance
                    "not_measured": [t["id"] for t in rep["targets"] if not measured(t)],
                    "undecided": [t["id"] for t in rep["targets"] if undecided(t, trusted(rep))],
                    "alignment_trusted": (rep.get("alignment") or {}).get("trusted"),
                    "sigma0_px": rep.get("sigma0_px")}
        return doc

    # --- trends ----------------------------------------------------------------------
    def _done_jobs(self, part: str) -> dict[str, dict]:
        """Index rows of the DONE jobs of ``part`` (its number or its name), by id."""
        self._drain()
        return {r["id"]: r for r in self._rows(part, None, status="DONE")}

    def job_targets(self, part: str) -> list[str]:
        """Target ids measured in the finished jobs of ``part`` (from the index), sorted."""
        names = {r["part"] for r in self._done_jobs(part).values() if r.get("part")}
        ids = sorted({t for name in names for t in self.index.part_targets(name)})
        if not ids:
            raise NotFound(f"no finished job of part {part!r}")
        return ids

    def target_trend(self, part: str, target: str, axis: str = "norm") -> dict:
        """One target's deviation over the part's jobs (or a group's: ``target`` = ids joined by commas).

        ``axis``: ``norm`` (|deviation|, one-sided: 0..tolerance) or ``x``/``y``/``z`` (a signed component
        in the part frame, two-sided: -tolerance..+tolerance). ``value_m`` is the charted value; for a
        group it is the group's worst per part (largest |d|, or the component farthest from zero), with
        ``target`` naming which one. One index query per target (and part name), no folder read.

        Every measurement is a point, but not every point is a statistic's: a point of a job whose verdict is
        UNTRUSTED (the alignment to CAD) or whose decision does not decide (inconclusive: within U of the
        tolerance, suspect or doubtful; undecided) has ``excluded`` saying why (None for the others), and the
        control limits, Cp/Cpk and rules leave it out (:func:`cell.web.service.trend`). ``tolerance_m`` (the
        USL) is the newest job's tolerance; each point carries its own.
        """
        if axis not in ("norm", "x", "y", "z"):
            raise InputError(f"axis {axis!r}: norm, x, y or z")
        group = [t.strip() for t in target.split(",") if t.strip()]
        if not group or len(group) > 500:
            raise InputError("name one target, or a group of up to 500 separated by commas")
        done = self._done_jobs(part)
        names = sorted({r["part"] for r in done.values() if r.get("part")})
        members = list(dict.fromkeys(group))
        per_target: list[dict[str, dict]] = []  # per group member: job id -> its trend point
        for tid in members:
            pts_t = {}
            for name in names:
                for p in self.index.target_trend(name, tid):
                    if p["job_id"] in done and p["deviation_norm_m"] is not None and \
                            (axis == "norm" or p["deviation"] is not None):
                        pts_t[p["job_id"]] = p
            per_target.append(pts_t)
        # a part where the group was not all measured is no point of the trend
        jobs = set.intersection(*(set(d) for d in per_target)) if per_target else set()
        order = sorted(jobs, key=lambda j: (per_target[0][j]["finished"] or "", j))
        pts = []
        for jid in order:
            cand = []
            for tid, d in zip(members, per_target):
                t = d[jid]
                v = t["deviation_norm_m"] if axis == "norm" else t["deviation"]["xyz".index(axis)]
                cand.append((abs(v) / t["tolerance_m"], v, t, tid))
            tols = [c[2]["tolerance_m"] for c in cand]
            if len(group) > 1 and (max(tols) - min(tols)) > 1e-12:
                raise InputError(f"the targets {target!r} have different tolerances in {jid}: a group trend needs one "
                                 "tolerance")
            _, v, t, tid = max(cand, key=lambda c: c[0])
            # a group's worst is only known when every member's decision decides
            why = next((f"{c[3]}: {w}" if len(group) > 1 else w for c in cand
                        if (w := exclusion({"deviation_norm_m": c[2]["deviation_norm_m"], "decision": c[2]["decision"]},
                                           done[jid].get("verdict"))) is not None), None)
            pts.append({"job_id": jid, "serial": t["serial"] or done[jid].get("serial"), "finished": _utc_ms(t["finished"]),
                        "deviation_norm_m": t["deviation_norm_m"], "value_m": v, "sigma_m": t["sigma_m"],
                        "pass": t["pass"], "target": tid, "tolerance_m": t["tolerance_m"], "decision": t["decision"],
                        "verdict": done[jid].get("verdict"), "excluded": why})
        if not pts:
            raise NotFound(f"no measurement of target {target!r} in the finished jobs of part {part!r}")
        tol = float(pts[-1]["tolerance_m"])  # the newest job's: a tolerance changed by the drawing applies from then
        lsl, usl = (None, tol) if axis == "norm" else (-tol, tol)
        return {"part": part, "target": target, "group": group, "axis": axis, "points": pts, "tolerance_m": tol,
                "lsl": lsl, "usl": usl}


def reverifications(root: Path) -> list[dict]:
    """The cell's reverification records (scale-bar length errors against the MPE), oldest first."""
    from cell.cellcal.common import CAL_DIR

    out = []
    base = Path(root) / CAL_DIR
    for f in sorted(base.glob("*/reverification.json")) if base.is_dir() else []:
        try:
            d = json.loads(f.read_text())
        except (OSError, ValueError):
            continue
        out.append({"record": f.parent.name, "cell": d.get("cell"), "finished": d.get("finished"),
                    "passed": d.get("passed"), "detail": d.get("detail"),
                    "positions": [{"position": p.get("position"), "error_m": p.get("error_m"), "mpe_m": p.get("mpe_m")}
                                  for p in d.get("positions", [])]})
    out.sort(key=lambda r: r["finished"] or "")
    return out
