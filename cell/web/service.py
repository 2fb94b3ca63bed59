"""What the console does, for pages and API alike: start, resume, abort, acknowledge, sign off.

Every action that changes something is recorded with who and when twice: in the console's audit
table (in the archive folder) and as an ``audit`` record in the job's own journal.
"""
from __future__ import annotations

import csv
import io
import json
import os
import shutil
import subprocess
import tempfile
from functools import lru_cache
from pathlib import Path

from calibration.errors import InputError
from cell.jobspec import load_job
from cell.record.decisions import measured, undecided
from cell.record.decisions import trusted as frame_trusted
from cell.record.jobfolder import JobFolder, atomic_write_bytes
from cell.record.runinfo import clean_serial
from cell.web.runner import Busy, CellRunner, live_state, operator_advice
from cell.web.store import ArchiveView, NotFound, job_folder
from cell.web.users import UserStore


class Console:
    """The console's state: the archive it reads, the runner it drives, the users it knows."""

    def __init__(self, archive: Path, programs: Path, users: UserStore, cell_id: str | None = None,
                 chromium: str | None = None, archive_url: str | None = None):
        self.root = Path(archive).resolve()
        self.programs_dir = Path(programs).resolve()
        self.users = users
        self.view = ArchiveView(self.root, archive_url)
        self.runner = CellRunner(self.root, cell_id, self.view.url)
        self.chromium = chromium or next((p for p in (shutil.which("chromium"), shutil.which("chromium-browser"),
                                                      shutil.which("google-chrome")) if p), None)

    # --- part programs ------------------------------------------------------------------
    def programs(self) -> dict[str, Path]:
        """Part programs: job files kept as templates, ``NAME.toml`` or ``NAME/job.toml`` in the programs folder."""
        out = {}
        if self.programs_dir.is_dir():
            for p in sorted(self.programs_dir.glob("*.toml")):
                out[p.stem] = p
            for p in sorted(self.programs_dir.glob("*/job.toml")):
                out.setdefault(p.parent.name, p)
        return out

    def program(self, name: str) -> Path:
        progs = self.programs()
        if name not in progs:  # only names from the listing: no path from the request reaches the disk
            raise NotFound(f"no part program {name!r}")
        return progs[name]

    def save_program(self, name: str, text: str, user: str) -> None:
        """Replace a part program's text after validating it as a job file (nothing written when invalid)."""
        path = self.program(name)
        tmp = path.with_name(f".{path.name}.check")
        tmp.write_text(text, encoding="utf-8")
        try:
            load_job(tmp)
        except InputError as exc:
            raise InputError(str(exc).replace(str(tmp), path.name)) from None
        finally:
            tmp.unlink(missing_ok=True)
        atomic_write_bytes(path, text.encode("utf-8"))
        self.users.audit(user, "edit program", None, name)

    # --- audit ----------------------------------------------------------------------------
    def audit(self, user: str, action: str, job_id: str | None, detail: str = "") -> None:
        self.users.audit(user, action, job_id, detail)
        if job_id is None:
            return
        folder = self.runner.folder_of(job_id)
        if folder is None:
            return
        jf = JobFolder(folder)
        try:
            lock = jf.lock()
        except InputError:  # the job is running: its runner closes the folder (manifest) when it ends
            for _ in range(3):
                try:
                    JobFolder(self.runner.folder_of(job_id) or folder).append("audit", user=user, action=action,
                                                                                detail=detail)
                    break
                except FileNotFoundError:  # moved from .incoming into the archive just now
                    continue
            return
        try:
            jf.append("audit", user=user, action=action, detail=detail)
            if (folder / "manifest.json").exists():
                jf.write_manifest()  # the folder stays closed, with the audit record in it
        finally:
            os.close(lock)

    # --- jobs -------------------------------------------------------------------------------
    def start(self, program: str, serial: str | None, user: str, placed: bool = True) -> str:
        if not placed:
            raise InputError("confirm that the part is placed on its fixture before starting")
        path = self.program(program)
        serial = clean_serial(serial)
        s = self.runner.start(path, serial, user)
        job_id = self.runner.job_id_of(s, wait_s=30.0)
        if job_id is None:
            s.proc.wait(timeout=60)
            doc = self.runner.result(s) or {}
            lines = self.runner.log_lines(s, 3)
            if any(ln.startswith("usage:") or ": error: " in ln for ln in lines) and not doc.get("message"):
                lines = []  # the command line refused (argparse): its usage text is the console's business, not the client's
            raise InputError(doc.get("message") or "; ".join(lines) or "the job did not start")
        self.audit(user, "start", job_id, f"program {program}, serial {serial or '-'}")
        return job_id

    def resume(self, job_id: str, user: str) -> str:
        job_folder(self.root, job_id)
        st = self.view.get_job(job_id)["state"]
        if st not in ("FAULTED", "ABORTED"):
            raise InputError(f"{job_id} is {st}: only a faulted or aborted job resumes")
        self.runner.resume(job_id, user)
        self.audit(user, "resume", job_id)
        return job_id

    def abort(self, job_id: str, user: str) -> bool:
        from cell.job import abort_job

        job_folder(self.root, job_id, staged=True)  # NotFound for anything that is not a job
        s = self.runner.session_of(job_id)
        if s is not None and s.alive():
            # journalled before the job is signalled: its runner, ending at once, writes its terminal record after the
            # request (the journal's order is the order of events)
            self.audit(user, "abort", job_id)
            if self.runner.abort(job_id, user):
                return True
            self.audit(user, "abort refused", job_id, "the job ended before the request reached it")
            raise InputError(f"{job_id} is not running on this cell")
        # a job this console did not start (cell run in a terminal): the same abort path, by its lock's pid
        if not abort_job(job_id, reason=f"console: {user}", archive_root=self.root):
            raise InputError(f"{job_id} is not running on this cell")
        self.audit(user, "abort", job_id)
        return True

    def acknowledge(self, job_id: str, user: str, note: str = "") -> None:
        st = self.view.get_job(job_id)["state"]
        if st != "FAULTED":
            raise InputError(f"{job_id} is {st}: only a fault is acknowledged")
        self.audit(user, "acknowledge fault", job_id, note[:500])

    def sign_off(self, job_id: str, user: str, note: str = "") -> None:
        st = self.view.get_job(job_id)["state"]
        if st != "DONE":
            raise InputError(f"{job_id} is {st}: only a finished job is signed off")
        self.audit(user, "sign off", job_id, note[:500])

    def status(self, job_id: str) -> dict:
        """The API's job document: {id, state, stage, progress, verdict} and what the live view shows."""
        folder = self.runner.folder_of(job_id)
        s = self.runner.session_of(job_id)
        if folder is None and s is not None and not s.alive():
            # refused for bad input before it reached the archive (a part out of reach...): nothing was kept
            doc = self.runner.result(s) or {}
            reason = doc.get("message") or doc.get("reason") or "; ".join(self.runner.log_lines(s, 2))
            return {"id": job_id, "state": "FAULTED", "stage": None, "progress": 0.0, "verdict": None,
                    "running": False, "reason": reason, "advice": operator_advice(reason), "time_left_s": None,
                    "stations_done": 0, "stations": None, "flange_xyz_m": [], "latest_image": None,
                    "log": self.runner.log_lines(s, 30), "kept": False}
        if folder is None:
            job_folder(self.root, job_id)  # NotFound for anything that is not a job
            raise NotFound(f"no job {job_id!r}")
        # whether the process runs, asked BEFORE its journal is read: a job that writes DONE and exits between the two
        # reads was shown FAULTED at its last stage, and the live view stopped there (seen under load in CI)
        running = s is not None and s.alive()
        live = live_state(folder)
        if s is not None and not running and live["state"] not in ("DONE", "FAULTED", "ABORTED"):
            live["state"] = "FAULTED"
            live["reason"] = "; ".join(self.runner.log_lines(s, 2))
        verdict = None
        if live["state"] == "DONE" and (folder / "report.json").exists():
            verdict = json.loads((folder / "report.json").read_text()).get("verdict")
        doc = {"id": job_id, "state": live["state"], "stage": live["stage"], "progress": live["progress"],
               "verdict": verdict, "running": running} | {k: v for k, v in live.items() if k not in ("state", "stage", "progress")}
        if live["state"] in ("FAULTED", "ABORTED"):
            doc["advice"] = operator_advice(live["reason"])
        doc["log"] = self.runner.log_lines(s, 30) if s is not None else []
        if s is not None and s.program:
            doc["program"] = Path(s.program).parent.name if Path(s.program).name == "job.toml" else Path(s.program).stem
        return doc

    def running(self) -> dict | None:
        s = self.runner.current
        if s is None or not s.alive():
            other = self.runner.external_running()
            return None if other is None else {"job_id": other, "user": "a terminal ('cell run')", "program": ""}
        return {"job_id": self.runner.job_id_of(s), "user": s.user, "program": Path(s.program).stem if s.program else ""}

    # --- exports ------------------------------------------------------------------------
    def report_csv(self, job_id: str) -> str:
        """One row per target; the coordinates are the CAD nominal's (``nominal_*_mm``), the deviation measured.

        ``pass`` is ``yes``/``no`` (|d| within / beyond the tolerance) only where the measurement decides: where
        the decision is inconclusive (within U of the tolerance, a suspect or doubtful measurement) or undecided
        (the alignment to CAD not trusted, or any UNTRUSTED verdict) it is left EMPTY, as it is for a target not
        measured. Empty rather than the decision word: a column a spreadsheet filters on yes/no keeps two values
        and a blank, and the word is in ``decision`` next to it. ``verdict`` (the part's) and ``alignment_trusted`` (``yes``/``no``)
        close every row, after the columns the file always had.
        """
        rep = self.view.report(job_id)
        if rep is None:
            raise NotFound(f"{job_id} has no report (not DONE)")
        part = rep.get("part") or {}
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(["job_id", "part_number", "revision", "serial", "target", "nominal_x_mm", "nominal_y_mm",
                    "nominal_z_mm", "dx_um", "dy_um", "dz_um", "deviation_um", "tolerance_um", "U_k2_um",
                    "sigma_um", "pass", "decision", "verdict", "alignment_trusted"])

        def f(v, k):
            return "" if v is None else f"{v * k:.4f}"

        verdict = rep.get("verdict") or ""
        trusted = (rep.get("alignment") or {}).get("trusted")
        trusted = "" if trusted is None else ("yes" if trusted else "no")
        frame = frame_trusted(rep)
        for t in rep["targets"]:
            decided = measured(t) and not undecided(t, frame)
            w.writerow([csv_text(job_id), csv_text(part.get("number") or ""), csv_text(part.get("revision") or ""),
                        csv_text(part.get("serial") or ""), csv_text(t["id"]),
                        *(f(v, 1e3) for v in t["nominal"]), *(f(v, 1e6) for v in t["deviation"]),
                        f(t["deviation_norm_m"], 1e6), f(t["tolerance_m"], 1e6), f(t.get("uncertainty_U_m"), 1e6),
                        f(t.get("achieved_sigma_m"), 1e6), ("yes" if t["pass"] else "no") if decided else "",
                        csv_text(t.get("decision") or ""), csv_text(verdict), trusted])
        return buf.getvalue()

    def report_pdf(self, job_id: str) -> bytes:
        """report.html printed to PDF by headless Chromium (the same HTML the browser shows)."""
        folder = job_folder(self.root, job_id)
        html = folder / "report.html"
        if not html.exists():
            raise NotFound(f"{job_id} has no report (not DONE)")
        if self.chromium is None:
            raise InputError("PDF export needs Chromium on this computer (apt-get install chromium)")
        with tempfile.TemporaryDirectory(prefix="cell-pdf-") as tmp:
            out = Path(tmp) / "report.pdf"
            cmd = [self.chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                   "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-extensions",
                   f"--user-data-dir={tmp}/profile", "--no-pdf-header-footer", "--virtual-time-budget=10000",
                   f"--print-to-pdf={out}", html.resolve().as_uri()]
            p = subprocess.run(cmd, capture_output=True, timeout=180)
            if p.returncode != 0 or not out.exists():
                raise InputError(f"Chromium could not print the report (exit {p.returncode})")
            return out.read_bytes()


__all__ = ["Busy", "Console", "NotFound"]


def default_baseline(n: int) -> int:
    """Parts whose spread sets the control limits when the user names none: all of them (a retrospective,
    phase I chart). Naming a reference period (``baseline``: the first k parts) gives phase II limits, which a
    later drift cannot widen, at the price of a noisier sigma when k is small."""
    return n


def trend(view: ArchiveView, part: str, target: str, axis: str = "norm", baseline: int | None = None) -> dict:
    """A target's trend over serial parts with its I-MR analysis (the API's trend document).

    ``points`` holds every measurement; those with ``excluded`` (a job UNTRUSTED, a decision that does not decide:
    :meth:`ArchiveView.target_trend`) are shown but left out of the centre, limits, rules and Cp/Cpk, which are of
    the ``n_used`` others (``baseline``: the first k of those). ``moving_range`` and a violation's ``index`` are per
    point of ``points`` (an excluded point has no moving range; the next used point's is to the used one before).
    """
    from cell.web.spc import analyse

    t = view.target_trend(part, target, axis)
    used = [i for i, p in enumerate(t["points"]) if not p.get("excluded")]
    vals = [t["points"][i]["value_m"] for i in used]
    n_excl = len(t["points"]) - len(used)
    if len(vals) < 2:
        raise InputError(f"target {target!r} of part {part!r} has {len(vals)} measurement(s) a trend can use"
                         + (f" ({n_excl} left out: alignment not trusted, or a decision that does not decide)"
                            if n_excl else "") + ": a trend needs two")
    if baseline is None:
        baseline = default_baseline(len(vals))
    if not 2 <= baseline <= len(vals):
        raise InputError(f"baseline {baseline}: between 2 and {len(vals)} parts")
    a = analyse(vals, t["lsl"], t["usl"], baseline)
    for v in a["violations"]:
        v["index"] = used[v["index"]]
        v["serial"] = t["points"][v["index"]]["serial"]
        v["job_id"] = t["points"][v["index"]]["job_id"]
    mr: list = [None] * len(t["points"])
    for k, i in enumerate(used):
        mr[i] = a["moving_range"][k]
    a["moving_range"] = mr
    return t | {k: a[k] for k in ("center", "sigma_within", "ucl", "lcl", "mr_bar", "mr_ucl", "baseline",
                                  "moving_range", "violations", "capability", "cp", "cpk")} | {
        "n_used": len(used), "n_excluded": n_excl}


def csv_text(v):
    """A text cell for a CSV a spreadsheet opens: one that starts with ``= + - @``, a tab or a CR would be read as a
    formula (a serial ``=HYPERLINK(...)``), so it gets a leading ``'`` (OWASP's CSV injection advice). Only for the
    text columns: the numbers are written by the exporters themselves, and a negative number stays a number."""
    if isinstance(v, str) and v[:1] in ("=", "+", "-", "@", "\t", "\r"):
        return "'" + v
    return v


def trend_csv(doc: dict) -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["part", "target", "axis", "n", "serial", "job_id", "finished", "value_um", "deviation_um",
                "moving_range_um", "center_um", "ucl_um", "lcl_um", "lsl_um", "usl_um", "rules", "tolerance_um",
                "excluded"])
    um = lambda v: "" if v is None else f"{v * 1e6:.3f}"  # noqa: E731
    for i, p in enumerate(doc["points"]):
        rules = " ".join(sorted({v["rule"] for v in doc["violations"] if v["index"] == i}))
        w.writerow([csv_text(doc["part"]), csv_text(doc["target"]), csv_text(doc["axis"]), i + 1, csv_text(p["serial"] or ""),
                    csv_text(p["job_id"]), csv_text(p["finished"]),
                    um(p["value_m"]), um(p["deviation_norm_m"]), um(doc["moving_range"][i]), um(doc["center"]),
                    um(doc["ucl"]), um(doc["lcl"]), um(doc["lsl"]), um(doc["usl"]), rules, um(p.get("tolerance_m")),
                    csv_text(p.get("excluded") or "")])
    return buf.getvalue()


def latest_image_jpeg(folder: Path, max_width: int = 960) -> bytes | None:
    """The job's latest image with the detections found in it drawn (green circles, ids), as JPEG."""
    import cv2

    recs = [r for r in JobFolder(folder).read_journal()[0] if r.get("event") == "station_done"]
    if not recs:
        return None
    rec = recs[-1]
    img = cv2.imread(str(folder / rec["image"]), cv2.IMREAD_COLOR)
    if img is None:
        return None
    uv = _detections(folder, rec["station"])
    label = "detections"
    if uv is None:  # not measured yet (ACQUIRE): the dots the detector finds now, before identification
        uv = _preview_detections(str(folder / rec["image"]), rec.get("sha256", ""))
        label = "dots found (not yet identified)"
    scale = min(1.0, max_width / img.shape[1])
    if scale < 1.0:
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    r = max(4, int(8 * scale))
    for u, v in uv:
        cv2.circle(img, (int(round((u + 0.5) * scale - 0.5)), int(round((v + 0.5) * scale - 0.5))), r, (0, 200, 0), 2)
    cv2.putText(img, f"station {rec['station']}: {len(uv)} {label}", (10, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7,
                (0, 220, 255), 2)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 80])
    return buf.tobytes() if ok else None


@lru_cache(maxsize=8)
def _preview_detections(path: str, sha256: str) -> list:
    """Dot centres in an image not measured yet (the detector of MEASURE, without identification)."""
    import cv2

    from calibration.targets import detect_retro_targets

    img = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
    if img is None:
        return []
    return detect_retro_targets(img).uv.tolist()


def _detections(folder: Path, station: str) -> list | None:
    """Detections of one station: observations.json once MEASURE is done, else the run log's /detections
    (None when neither has them yet)."""
    obs = folder / "observations.json"
    if obs.exists():
        try:
            for o in json.loads(obs.read_text()).get("images", []):
                if o.get("station") == station:
                    return o.get("uv") or []
        except (ValueError, AttributeError):
            pass
    from mcap.reader import NonSeekingReader

    found: list | None = None
    for log in sorted(folder.glob("run*.mcap")):
        try:
            with open(log, "rb") as f:
                for _s, ch, msg in NonSeekingReader(f, validate_crcs=False).iter_messages(topics=["/detections"]):
                    d = json.loads(msg.data)
                    if d.get("station") == station:
                        found = d.get("uv") or []
        except Exception:  # a log being written: what was read so far counts
            pass
    return found
