"""The archive index's two console queries on PostgreSQL and on SQLite (target: each < 200 ms).

Run from the repository root:  .venv/bin/python benchmarks/bench_archive.py [--jobs 100000] [--url postgresql://...]

Loads the same synthetic archive into a PostgreSQL server (started here in a temporary folder from
Debian's postgresql package, as the tests do, unless ``--url`` names one) and into an SQLite index:
``--jobs`` jobs of ``--parts`` parts (so ``jobs / parts`` jobs of each part), ``--targets`` targets
each. Then times, best and median of ``--repeat``:

* trend: ``target_trend(part, target)``: one target over every job of its part (10,000 points at
  the defaults), as the console's trend page asks for it, rows turned into dicts;
* list page: ``list_jobs(limit=50)`` + ``count_jobs()`` newest first over every job (the console's
  first page with its total), and the same filtered by part and verdict at page 20.

Prints each figure for both backends and PostgreSQL / SQLite as the ratio (the baseline is SQLite,
embedded, in the same process on the same data).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from cell.record.archive import open_index  # noqa: E402
from cell.record.archive.tables import COV_KEYS  # noqa: E402


def rows(n_jobs: int, n_parts: int, n_targets: int, chunk: int, seed: int = 0):
    """Chunks of (job rows, target rows): job k of part k % n_parts, one every 37 s."""
    rng = np.random.default_rng(seed)
    t0 = datetime(2025, 1, 1, tzinfo=timezone.utc)
    now = datetime.now(timezone.utc)
    nominal = rng.uniform(-0.1, 0.1, (n_parts, n_targets, 3))
    for start in range(0, n_jobs, chunk):
        jr, tr = [], []
        ks = np.arange(start, min(n_jobs, start + chunk))
        dev = rng.normal(0, 30e-6, (len(ks), n_targets, 3))
        norm = np.linalg.norm(dev, axis=2)
        for i, k in enumerate(ks):
            part = f"part-{k % n_parts}"
            started = t0 + timedelta(seconds=37 * int(k))
            finished = started + timedelta(seconds=300)
            failed = int((norm[i] > 100e-6).sum())
            jr.append({"id": f"job-{k:06d}", "name": part, "part": part, "serial": f"SN{k:06d}", "cell_id": f"cell{k % 8}",
                       "status": "DONE", "verdict": "FAIL" if failed else "PASS", "started": started,
                       "finished": finished, "targets": n_targets, "failed": failed, "sigma0_px": 0.9,
                       "origin": f"cell{k % 8}:/archive", "folder": f"/archive/job-{k:06d}", "manifest_sha256": "0" * 64,
                       "indexed_at": now})
            for t in range(n_targets):
                d = dev[i, t]
                row = {"job_id": f"job-{k:06d}", "target_id": f"T{t:03d}", "part": part, "finished": finished,
                       "serial": f"SN{k:06d}",
                       "kind": "retro", "deviation_norm_m": float(norm[i, t]), "tolerance_m": 100e-6,
                       "uncertainty_u_m": 20e-6, "achieved_sigma_m": 17e-6, "decision": "conforming" if norm[i, t] < 80e-6 else "inconclusive",
                       "passed": bool(norm[i, t] <= 100e-6)}
                for a, j in zip("xyz", range(3)):
                    row[f"nominal_{a}"] = float(nominal[k % n_parts, t, j])
                    row[f"measured_{a}"] = float(nominal[k % n_parts, t, j] + d[j])
                    row[f"deviation_{a}"] = float(d[j])
                for c in COV_KEYS:
                    row[f"cov_{c}"] = 1e-10 if c[0] == c[1] else 1e-11
                tr.append(row)
        yield jr, tr


def load(ix, args) -> float:
    t = time.perf_counter()
    for jr, tr in rows(args.jobs, args.parts, args.targets, chunk=2000):
        ix.bulk_load(jr, tr)
    # what autovacuum does after a bulk of inserts (PostgreSQL: the visibility map that lets a trend be an
    # index-only scan; both: statistics)
    if ix.kind == "postgresql":
        with ix.engine.connect().execution_options(isolation_level="AUTOCOMMIT") as conn:
            conn.exec_driver_sql("VACUUM ANALYZE")
    else:
        with ix.engine.begin() as conn:
            conn.exec_driver_sql("ANALYZE")
    return time.perf_counter() - t


def timed(fn, repeat: int) -> tuple[float, float, object]:
    fn()  # warm (plans, caches): the console asks the same queries again and again
    ts, out = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t)
    return min(ts), statistics.median(ts), out


def queries(ix, args) -> dict:
    per_part = args.jobs // args.parts
    trend = timed(lambda: ix.target_trend("part-3", "T007"), args.repeat)
    assert len(trend[2]) == per_part, f"trend returned {len(trend[2])} points, expected {per_part}"
    page = timed(lambda: (ix.list_jobs(limit=50), ix.count_jobs()), args.repeat)
    assert len(page[2][0]) == 50 and page[2][1] == args.jobs
    filt = timed(lambda: (ix.list_jobs(part="part-3", verdict="FAIL", limit=50, offset=50 * 19),
                          ix.count_jobs(part="part-3", verdict="FAIL")), args.repeat)
    return {"trend": trend[:2], "list page": page[:2], "filtered page 20": filt[:2]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=100_000)
    ap.add_argument("--parts", type=int, default=10)
    ap.add_argument("--targets", type=int, default=10)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--url", help="an empty PostgreSQL database to use (default: start a server here)")
    args = ap.parse_args()
    server = None
    url = args.url
    if url is None:
        from pgserver import PgServer, _bindir

        if _bindir() is None:
            print("no PostgreSQL server installed (apt-get install postgresql) and no --url: cannot run")
            return 2
        server = PgServer(_bindir())
        url = server.url
    tmp = Path(tempfile.mkdtemp(prefix="bench-archive-"))
    results = {}
    try:
        for name, u in (("postgresql", url), ("sqlite", f"sqlite:///{tmp / 'index.sqlite'}")):
            ix = open_index(u)
            secs = load(ix, args)
            print(f"{name}: loaded {args.jobs} jobs x {args.targets} targets in {secs:.1f} s", flush=True)
            results[name] = queries(ix, args)
            ix.close()
    finally:
        if server is not None:
            server.close()
        import shutil

        shutil.rmtree(tmp, ignore_errors=True)
    per_part = args.jobs // args.parts
    what = {"trend": f"trend of one target over {per_part} jobs",
            "list page": f"list page (50 newest + total) over {args.jobs} jobs",
            "filtered page 20": f"list page 20 filtered by part and verdict over {args.jobs} jobs"}
    load1, load5, _ = os.getloadavg()
    print(f"\nmachine: {os.cpu_count()} cores, load average {load1:.1f} (1 min) {load5:.1f} (5 min) at the end")
    print(f"{'query':<62} {'PostgreSQL best/median':>24} {'SQLite best/median':>22} {'PG/SQLite':>10}")
    for key in what:
        (pb, pm), (sb, sm) = results["postgresql"][key], results["sqlite"][key]
        ok = "ok" if pm < 0.2 else "OVER 200 ms"
        print(f"{what[key]:<62} {pb * 1e3:10.1f} / {pm * 1e3:6.1f} ms {sb * 1e3:9.1f} / {sm * 1e3:6.1f} ms "
              f"{pm / sm:9.2f}x  {ok}")
        print("BENCHMARK " + json.dumps({"what": f"archive: {what[key]} (PostgreSQL, median)",
                                         "figure": f"{pm * 1e3:.1f} ms", "baseline": f"SQLite {sm * 1e3:.1f} ms",
                                         "ratio": f"{pm / sm:.2f}"}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
