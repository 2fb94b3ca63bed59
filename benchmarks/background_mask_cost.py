"""What ``[camera] background_mask = "cad"`` costs MEASURE per image (docs/decisions/0035).

Views all around the example part are rendered by the simulated camera (sensor noise), and each image is measured
by ``cell.stages.imaging.measure_image`` as MEASURE does (named at a pose a few mm off), once without and once with
the CAD's surface labels (detect, name, resect, label, detect and name again). Printed: ms per image for each,
their ratio, and the named dots of each (they should be the same).

    .venv/bin/python -m benchmarks.background_mask_cost [--views 12]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration.camera import invert, look_at  # noqa: E402
from cell.devices import make_job_sim_cell  # noqa: E402
from cell.loadedjob import load  # noqa: E402
from cell.stages.imaging import measure_image  # noqa: E402
from cell.stages.surface_labels import SurfaceLabeller  # noqa: E402
from planning.visibility import Occluder  # noqa: E402

JOB = Path(__file__).resolve().parents[1] / "examples" / "bracket" / "job.toml"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    job = load(JOB)
    sim = make_job_sim_cell(job, nominal_lens=True)  # truth: the nominal lens's projection
    sim.camera.rng = np.random.default_rng(a.seed)
    rng = np.random.default_rng(a.seed)
    centre = sim.world.true_xyz.mean(axis=0)
    occ = Occluder(job.part.mesh)
    t0 = time.perf_counter()
    surfaces = SurfaceLabeller(job.part.mesh)
    t_build = time.perf_counter() - t0
    times, named = np.zeros(2), np.zeros(2, dtype=int)
    for k in range(a.views):
        az = 2 * np.pi * k / a.views + rng.uniform(-0.2, 0.2)
        el = np.deg2rad(rng.uniform(20, 80))
        eye = centre + rng.uniform(0.35, 0.6) * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        part_from_cam = look_at(eye, centre + rng.normal(0, 0.02, 3), roll_rad=rng.uniform(-np.pi, np.pi))
        img, _ = sim.camera.render(part_from_cam, noise=True)
        approx = invert(part_from_cam)
        approx[:3, 3] += rng.normal(0, 0.002, 3)
        for i, s in enumerate((None, surfaces)):
            t0 = time.perf_counter()
            m, _ = measure_image(img, job.part, job.intrinsics, approx, occ, coded_family=job.spec.job.coded_family,
                                 surfaces=s)
            times[i] += time.perf_counter() - t0
            named[i] += len(m.target)
    per = 1e3 * times / a.views
    print(f"{a.views} images of the example: measure_image {per[0]:.0f} ms per image without the mask, {per[1]:.0f} ms "
          f"with it (ratio {per[1] / per[0]:.2f}, +{per[1] - per[0]:.0f} ms); the labeller's set-up {1e3 * t_build:.0f} "
          f"ms once per job; dots named {named[0]} / {named[1]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
