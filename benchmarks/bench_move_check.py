"""Benchmark: VALIDATE's move checks around a dense part (a generated skin of about 70,000 faces).

VALIDATE checks each move between stations by conservative advancement: a distance query at every step.
Against a part mesh of tens of thousands of faces, the distance of a link far from it cost tens of milliseconds
(coal's bounding volumes prune poorly at range). The part's convex hull stands in where it is farther than
``PART_EXACT_WITHIN_M`` beyond the clearance (a lower bound there; the mesh itself nearer: decision 0055). The
baseline, in the same process, is the exact mesh everywhere (``HULL_STAND_IN_FACES`` raised). Both validate the
stored plan of tests.partgen seed 103 (``tests/data/validate_retour_partgen103.json``), whose tour must be made
again around a colliding move; the two must agree on every move.

Run: .venv/bin/python -m benchmarks.bench_move_check
"""
from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np

import planning.kinematics as kin
from cell.loadedjob import load
from cell.setup import collision_world, robot_model
from planning.execution import validate_plan

REPO = Path(__file__).resolve().parents[1]


def run(job) -> tuple[float, object]:
    doc = json.loads((REPO / "tests" / "data" / "validate_retour_partgen103.json").read_text())
    T = np.array([s["part_from_cam"] for s in doc["stations"]])
    ids = [s["id"] for s in doc["stations"]]
    t0 = time.perf_counter()
    ep = validate_plan(robot_model(job), T, job.spec.base_from_part(), job.spec.flange_from_cam(), collision_world(job),
                       ids=ids)
    return time.perf_counter() - t0, ep


def main() -> None:
    import sys

    sys.path.insert(0, str(REPO))
    from tests.partgen import make_part_job

    with tempfile.TemporaryDirectory() as tmp:
        job = load(make_part_job(Path(tmp) / "job", np.random.default_rng(103)).job)
        print(f"part: {len(job.part.mesh.faces)} faces")
        t_hull, ep = run(job)
        stand_in = kin.HULL_STAND_IN_FACES
        kin.HULL_STAND_IN_FACES = 10**9
        try:
            t_exact, ep0 = run(job)
        finally:
            kin.HULL_STAND_IN_FACES = stand_in
    steps = sum(m.n_checks for m in ep.moves)
    steps0 = sum(m.n_checks for m in ep0.moves)
    same = [ep.ids[i] for i in ep.order] == [ep0.ids[i] for i in ep0.order] and \
        [m.free for m in ep.moves] == [m.free for m in ep0.moves]
    print(f"validate with the hull stand-in: {t_hull:.2f} s ({steps} distance queries)")
    print(f"validate on the exact mesh (baseline): {t_exact:.2f} s ({steps0} distance queries)")
    print(f"ratio: {t_exact / t_hull:.1f}x faster; same tour and verdicts: {same}")


if __name__ == "__main__":
    main()
