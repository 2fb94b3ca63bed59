"""The loaded job: the job file, the part (mesh + targets), the camera and the cell, checked together.

Used by every stage and by the cell's own calibration jobs; the LOAD stage is :mod:`cell.stages.load`.

The simulated part's unknowns are resolved against the part here, with the job's other target ids: ``[sim]
deviations`` (a displacement per target) and ``[sim] damaged_targets`` (worn dots: each one's index and its
validated entry, refused when the id is unknown or names a coded target). Only the simulated cell gets them
(:func:`cell.devices.make_job_sim_cell`); PLAN's twin renders the nominal part."""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from calibration.camera import Intrinsics
from calibration.errors import CalibrationError, JobSpecError
from cell.jobspec import DamagedTarget, JobSpec, damaged_target_rows, load_deviations, load_job, resolve
from cell.thermal import bar_at_measurement, sim_expansion
from planning.part import Part, load_part
from planning.symmetry import symmetry_summary

#: a target's tolerance beyond this share of the part's largest extent is taken for one in another unit
TOLERANCE_MAX_SHARE = 0.25


@dataclass
class LoadedJob:
    """Everything LOAD produces, in SI units.

    Attributes:
        spec: the validated job file.
        path: the job file.
        folder: where its relative paths resolve.
        part: mesh and targets (metres, part frame).
        intrinsics: the camera's lens the job starts from: the cell's (``[cell] camera_lens`` of the cell file the
            job names, written by its hand-eye calibration), else the ``[camera]`` section's.
        deviations: (n, 3) true displacement of each target for the simulated cell (metres): ``[sim] deviations``,
            a mis-stated thickness and the expansion at ``[sim] part_C`` / ``bars_C``.
        tolerance_m: (n,) tolerance per target.
        scale_bars: ``(index_a, index_b, length_m, sigma_m)`` per scale bar of the job file (``[job] scale_bar`` or
            ``scale_bars``, in their order); empty without one. A bar of its own material under ``[thermal]``: its
            length at the bars' temperature in units of the part at 20 C (:func:`cell.thermal.bar_at_measurement`).
        target_thickness_m: how far the targets' faces stand above the CAD surface (``[job] target_thickness``). The
            part's target positions are the faces' centres, the CAD points lifted along their normals by it: what
            the camera sees and the cell measures. REPORT gives coordinates and deviations on the surface.
        damaged_targets: ``(index, entry)`` per ``[sim] damaged_targets`` entry: the worn dots of the simulated part
            (the index among the part's targets); empty without any.
        probe: the part thermometer's readings (``[thermal] part_C = "probe"``) once ADJUST resolved them into
            ``spec.thermal.part_C`` (:func:`cell.thermal.resolve_probe`); None before, or without a probe.
        cell: what the job took from the cell file it names (:func:`cell.cellcal.jobcell.cell_taken`: the file, its
            sha256, the hand-eye's calibration date and record, the lens); None when it names none.
    """

    spec: JobSpec
    path: Path
    folder: Path
    part: Part
    intrinsics: Intrinsics
    deviations: np.ndarray
    tolerance_m: np.ndarray
    scale_bars: tuple[tuple[int, int, float, float], ...] = ()
    target_thickness_m: float = 0.0
    damaged_targets: tuple[tuple[int, DamagedTarget], ...] = ()
    probe: dict | None = None
    cell: dict | None = None

    def surface_points(self, xyz: np.ndarray) -> np.ndarray:
        """Target face centres ``xyz`` (n, 3), part frame, -> the CAD surface points under them."""
        return np.asarray(xyz, dtype=float) - self.target_thickness_m * self.part.targets.normals

    def summary(self) -> dict:
        s, t = self.spec, self.part.targets
        return {
            "job": {"name": s.job.name, "file": str(self.path), "units": s.job.units, "seed": s.job.seed},
            # decision 0058: a layout that maps onto itself names every dot as its neighbour when the part is placed
            # one step off, and no image can tell
            "part": self.part.summary() | {"symmetry": symmetry_summary(t.xyz, t.normals, t.code)},
            "camera": self.intrinsics.to_dict() | {"sigma_px": s.camera.sigma_px,
                                                   "observation_weights": s.camera.observation_weights},
            "cell": {"robot": s.cell.robot, "backend": s.cell.backend, "obstacles": len(s.cell.obstacles),
                     "taken_from_cell_file": self.cell},
            "scale_bars": [{"a": self.part.targets.ids[a], "b": self.part.targets.ids[b], "length_m": L}
                           for a, b, L, _ in self.scale_bars],
            "sim_deviations": int((np.linalg.norm(self.deviations, axis=1) > 0).sum()),
            "sim_damaged_targets": len(self.damaged_targets),
            "target_thickness_m": self.target_thickness_m,
        }


def load(job_path: str | Path, overrides: dict[str, str] | None = None) -> LoadedJob:
    """Read, validate and load a job. Raises an ``InputError`` subclass with one clear line.

    ``overrides`` maps ``"section.key"`` to a replacement file path (an archived job
    points its mesh, targets and deviations at its own copies).
    """
    spec, folder = load_job(job_path, overrides)
    s = spec.scale
    j = spec.job
    part = load_part(
        resolve(folder, j.mesh),
        j.units,
        targets_csv=resolve(folder, j.targets) if j.targets else None,
        n_targets=j.n_targets,
        seed=j.seed,
        n_coded=j.n_coded,
        name=j.name,
        target_diameter_m=j.target_diameter * s,
        coded_size_m=j.coded_size * s,
        tessellation_tolerance=j.tessellation_tolerance,
    )
    thickness = (j.target_thickness or 0.0) * s
    if thickness > 0:  # the camera sees the targets' faces: the part's targets are their centres from here on
        part = replace(part, targets=replace(part.targets, xyz=part.targets.xyz + thickness * part.targets.normals))
    ids = part.targets.ids
    scale_bars = []
    index = part.targets.index()
    for key, bar in j.bars():
        for end in (bar.a, bar.b):
            if end not in index:
                raise JobSpecError(f"{job_path}: {key} names target {end!r}, which the part does not have")
        a, b = index[bar.a], index[bar.b]
        nominal = float(np.linalg.norm(part.targets.xyz[a] - part.targets.xyz[b]))
        length = bar.length * s
        if abs(nominal - length) > max(0.01 * length, 1e-3):
            raise JobSpecError(
                f"{job_path}: {key} length {bar.length} {j.units} differs from the CAD distance "
                f"{nominal / s:.4f} {j.units} between {bar.a} and {bar.b} by more than 1%"
            )
        # decision 0053: a bar of its own material at its length in units of the part at 20 C
        scale_bars.append((a, b, *bar_at_measurement(spec, bar, length, bar.sigma * s)))
    al = spec.alignment
    named = [("alignment.targets", t) for t in (al.targets or [])] + [("alignment.rps", t) for t in (al.rps or {})]
    index = part.targets.index()
    for key, tid in named:
        if tid not in index:
            raise JobSpecError(f"{job_path}: {key} names target {tid!r}, which the part does not have")
    if al.rps:
        from calibration.robust_alignment import rps_locks

        try:
            rps_locks({index[t]: a for t, a in al.rps.items()})
        except CalibrationError as exc:
            raise JobSpecError(f"{job_path}: alignment.rps: {exc}") from None
    deviations = np.zeros((len(ids), 3))
    if spec.sim.deviations:
        deviations = load_deviations(resolve(folder, spec.sim.deviations), ids, s)
    damaged = damaged_target_rows(spec, ids, part.targets.kind, job_path)
    if spec.sim.target_thickness is not None:  # the simulated targets are not as thick as the job says
        deviations = deviations + (spec.sim.target_thickness * s - thickness) * part.targets.normals
    # the simulated part and bars at their true temperatures (decision 0053)
    deviations = deviations + sim_expansion(spec, part.targets.xyz + deviations, [bar[:2] for bar in scale_bars])
    tol = part.targets.tolerance_m.copy()
    tol[~np.isfinite(tol)] = spec.report.tolerance * s
    size = float(np.max(part.mesh.extents))
    wide = np.flatnonzero(tol > TOLERANCE_MAX_SHARE * size)
    if len(wide):  # 250 meant in um, read in mm: the part PASSed with 0.4-0.6 mm deviations (an outside check)
        j = int(wide[0])
        raise JobSpecError(f"{job_path}: target {part.targets.ids[j]}'s tolerance {tol[j] / s:g} {spec.job.units} is "
                           f"{tol[j] / size:.0%} of the part's size ({size / s:g} {spec.job.units}; {len(wide)} such "
                           f"target(s)): a tolerance in another unit? ([report] tolerance, the targets file's "
                           "tolerance column)")
    intrinsics, taken = spec.intrinsics(), None
    if spec.cell.cell_file is not None:  # the lens calibrated with the cell's hand-eye (decision 0056)
        from cell.cellcal.jobcell import cell_taken

        taken = cell_taken(spec, Path(job_path))
        if taken["lens"] is not None:
            intrinsics = replace(intrinsics, **{k: v for k, v in taken["lens"].items() if k != "cov"})
    job = LoadedJob(
        spec=spec,
        path=Path(job_path),
        folder=folder,
        part=part,
        intrinsics=intrinsics,
        cell=taken,
        deviations=deviations,
        tolerance_m=tol,
        scale_bars=tuple(scale_bars),
        target_thickness_m=thickness,
        damaged_targets=damaged,
    )
    from cell.setup import part_placement_error  # a part in the table or an obstacle is refused here, at LOAD

    placed = part_placement_error(job)
    if placed:
        raise JobSpecError(f"{job_path}: {placed}")
    return job
