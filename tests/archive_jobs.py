"""Job folders written the way the job runner writes them, without running the pipeline.

For the archive tests (and the load test's cell processes): the journal and the state records
the runner appends, ``report.json`` with every judged target (nominal, measured, covariance,
deviation, decision) from a known truth, the manifest, and the archive calls the runner makes
(``record`` per transition, ``job_closed`` at the end). Nothing here is faked on the archive's
side: the folder and the index are the real ones.
"""
from __future__ import annotations

import numpy as np

from cell.record.archive import Archive
from cell.record.jobfolder import JobFolder, atomic_write_json, utc_now
from cell.states import STAGES

PART = "bracket"


def truth(job_index: int, n_targets: int, seed: int = 7) -> dict:
    """The known values of job ``job_index``: per target nominal, deviation, sigma."""
    nominal = np.random.default_rng(seed).uniform(-0.1, 0.1, (n_targets, 3))  # the same part every job
    rng = np.random.default_rng(1000 + job_index)
    dev = rng.normal(0.0, 30e-6, (n_targets, 3))
    dev[0] = [0.0, 0.0, 1e-6 * job_index]  # target T000 drifts 1 um per job: a trend to find
    sigma = rng.uniform(5e-6, 15e-6, n_targets)
    return {"nominal": nominal, "deviation": dev, "sigma": sigma}


def report_targets(job_index: int, n_targets: int, tol: float = 100e-6) -> list[dict]:
    t = truth(job_index, n_targets)
    out = []
    for i in range(n_targets):
        d = t["deviation"][i]
        s = t["sigma"][i]
        cov = np.diag([s * s, s * s, (2 * s) ** 2]) + 0.1 * s * s  # not diagonal: the off-diagonals count too
        norm = float(np.linalg.norm(d))
        U = 2 * float(np.sqrt(d @ cov @ d / max(norm * norm, 1e-300)))
        decision = "conforming" if norm + U <= tol else ("nonconforming" if norm - U > tol else "inconclusive")
        measured = t["nominal"][i] + d
        if i == n_targets - 1 and job_index % 5 == 4:  # every fifth job: the last target not measured
            out.append({"id": f"T{i:03d}", "kind": "retro", "nominal": t["nominal"][i].tolist(),
                        "measured": [None] * 3, "cov": [[None] * 3] * 3, "deviation": [None] * 3,
                        "deviation_norm_m": None, "tolerance_m": tol, "pass": False, "uncertainty_U_m": None,
                        "decision": None, "predicted_sigma_m": s, "achieved_sigma_m": None})
            continue
        out.append({"id": f"T{i:03d}", "kind": "retro", "nominal": t["nominal"][i].tolist(),
                    "measured": measured.tolist(), "cov": cov.tolist(), "deviation": d.tolist(),
                    "deviation_norm_m": norm, "tolerance_m": tol, "pass": norm <= tol, "uncertainty_U_m": U,
                    "decision": decision, "predicted_sigma_m": s, "achieved_sigma_m": float(np.sqrt(np.trace(cov)))})
    return out


def write_job(archive: Archive, job_id: str, job_index: int, n_targets: int = 20, serial: str | None = None,
              part: str = PART, between=None, untrusted: bool = False) -> JobFolder:
    """Write one whole job into ``archive`` as the runner does; ``between(stage)`` is called after each
    transition (the load test stops the database there). ``untrusted``: the alignment to CAD not trusted (verdict
    UNTRUSTED, every measured target undecided). Returns the closed folder."""
    f = JobFolder(archive.root / job_id)
    f.path.mkdir(parents=True)
    f.append("created", name=part, job_file="job.toml", backend="sim", serial=serial)
    state = "CREATED"
    for stage in [*STAGES, "DONE"]:
        to = stage.value if hasattr(stage, "value") else stage
        f.append("state", **{"from": state, "to": to})
        state = to
        if to == "ACQUIRE":
            recs = list(f.records())
            archive.record(job_id, name=part, part=part, status=to, started=recs[0]["t"])
        elif to not in ("LOAD", "PLAN", "VALIDATE"):
            archive.record(job_id, status=to)
        if to == "REPORT":
            tl = report_targets(job_index, n_targets)
            verdict = "PASS" if all(t["pass"] for t in tl) else "FAIL"
            if untrusted:
                verdict = "UNTRUSTED"
                for t in tl:
                    t["decision"] = "undecided" if t["decision"] is not None else None
            atomic_write_json(f.file("report.json"), {
                "job": {"id": job_id, "name": part, "part": part, "seed": job_index, "status": "DONE",
                        "started": list(f.records())[0]["t"], "finished": utc_now(), "versions": {}},
                "verdict": verdict, "images": 12, "sigma0_px": 0.9 + 0.001 * job_index,
                "part": {"number": "B-100", "revision": "A", "serial": serial}, "operator": "ann", "cell_id": None,
                "targets": tl})
        if between is not None:
            between(to)
    f.append("terminal", status="DONE", reason="")
    f.write_manifest()
    archive.job_closed(f.path)
    return f
