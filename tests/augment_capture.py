"""Run one job in this process and keep every closed-loop round's planning problem (for the exhaustive check).

    python tests/augment_capture.py JOB.toml ARCHIVE OUT.npz

The closed loop's planner (``planning.augment.plan_extra_stations``) is wrapped: each call's inputs, restricted
to the valid candidates, and the stations it chose are saved as ``r<k>_<name>`` arrays in OUT.npz. Run as a child
process by tests/test_closed_loop_hampered.py, like every whole job of the tests.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import planning.augment as augment  # noqa: E402
from cell.job import start_job  # noqa: E402


class _Quiet:
    def say(self, s: str) -> None:
        pass

    def progress(self, stage: str, fraction: float) -> None:
        pass


def main() -> int:
    job, archive, out = (Path(a) for a in sys.argv[1:4])
    rounds: dict[str, np.ndarray] = {}
    real = augment.plan_extra_stations

    def capture(N_have, rays_have, required, info, visible, valid, *, min_rays, max_new, consider=None):
        aug = real(N_have, rays_have, required, info, visible, valid, min_rays=min_rays, max_new=max_new,
                   consider=consider)
        k = len(rounds) // 8
        cand = np.flatnonzero(valid)
        pos = {int(c): i for i, c in enumerate(cand)}
        rounds.update({f"r{k}_N_have": np.asarray(N_have, dtype=float), f"r{k}_rays": np.asarray(rays_have),
                       f"r{k}_required": np.asarray(required, dtype=float),
                       f"r{k}_info": np.asarray(info[cand], dtype=float), f"r{k}_visible": np.asarray(visible[cand]),
                       f"r{k}_added": np.array([pos[int(a)] for a in aug.added], dtype=int),
                       f"r{k}_min_rays": np.array(min_rays), f"r{k}_max_new": np.array(max_new)})
        return aug

    augment.plan_extra_stations = capture
    res = start_job(job, archive, None, _Quiet())
    np.savez_compressed(out, status=np.array(res.status.value), **rounds)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
