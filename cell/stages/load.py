"""LOAD: the job file, its part (mesh and targets, checked), camera and deviations were loaded and checked
before the job folder existed (:func:`cell.loadedjob.load`); the stage records the part's summary."""
from __future__ import annotations

from cell.record.jobfolder import atomic_write_json


def run(ctx) -> None:
    """LOAD: the part summary into the job folder (the job itself was loaded and checked before the folder existed)."""
    atomic_write_json(ctx.folder.file("part.json"), ctx.job.summary())
