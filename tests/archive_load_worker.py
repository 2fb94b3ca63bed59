"""One cell of the archive load test: writes ``n`` jobs into its own folder, indexed in the shared database.

    python tests/archive_load_worker.py ROOT URL CELL N N_TARGETS [PUSH_DEST]

``CELL_LOAD_PACE_S`` (default 0): seconds each job lasts at least (a real job takes a minute; without
a pace, cheap jobs run through a two-second outage of the database before it is back).

Prints one JSON line: {``cell``, ``jobs`` (ids), ``outboxed`` (jobs that found the outbox
non-empty after closing: the database was away), ``pending`` (still in the outbox at the end)}.
"""
from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from archive_jobs import write_job  # noqa: E402
from cell.record.archive import Archive  # noqa: E402


def main(argv: list[str]) -> int:
    root, url, cell, n, n_targets = argv[:5]
    push = argv[5] if len(argv) > 5 else None
    a = Archive(Path(root), url, push=push)
    ids, outboxed = [], 0
    pace = float(os.environ.get("CELL_LOAD_PACE_S", "0"))
    for k in range(int(n)):
        t0 = time.monotonic()
        job_id = f"c{cell}-j{k:03d}"
        write_job(a, job_id, 100 * int(cell) + k, n_targets=int(n_targets), serial=f"SN-{cell}-{k:03d}")
        ids.append(job_id)
        outboxed += bool(a.outbox.pending())
        time.sleep(max(0.0, pace - (time.monotonic() - t0)))
    print(json.dumps({"cell": cell, "jobs": ids, "outboxed": outboxed, "pending": a.outbox.pending()}), flush=True)
    a.close()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
