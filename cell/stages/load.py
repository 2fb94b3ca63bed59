"""LOAD: the job file, its part (mesh and targets, checked), camera and deviations were loaded and checked
before the job folder existed (:func:`cell.loadedjob.load`); the stage records the part's summary, and says when the
targets' layout maps onto itself (decision 0058: a part placed one step off would have its dots named as their
neighbours, and no image can tell)."""
from __future__ import annotations

from cell.record.jobfolder import atomic_write_json


def run(ctx) -> None:
    """LOAD: the part summary into the job folder (the job itself was loaded and checked before the folder existed);
    a symmetric layout of the targets into the journal (``layout_symmetry``), the run log and the console."""
    summary = ctx.job.summary()
    atomic_write_json(ctx.folder.file("part.json"), summary)
    sym = summary["part"]["symmetry"]
    if sym["warning"]:
        ctx.folder.append("layout_symmetry", warning=sym["warning"], tol_m=sym["tol_m"],
                          symmetries=sym["symmetries"])
        ctx.log.log("warning", f"load: {sym['warning']}")
        ctx.say(f"  WARNING {sym['warning']}")
