"""The stages of a job, one module each, in the order of the state table (:mod:`cell.states`).

``close_loop`` adds stations after ADJUST for targets that miss their requirement (decision 0013).

Each stage is a function ``run(ctx)`` that reads what earlier stages wrote into the job folder and
writes its own result atomically before the state machine moves on. :data:`STAGE_FUNCTIONS` maps
every working :class:`~cell.states.State` to its stage; the runner (:mod:`cell.job`) reads this
table, checked at import against the state table.

``imaging`` (the image chain shared by MEASURE and the cell's calibration jobs) lives beside them.
"""
from __future__ import annotations

from typing import Callable

from cell.stages import acquire, adjust, calibrate, close_loop, load, measure, plan, report, validate
from cell.states import STAGES, State

StageFunction = Callable[[object], None]

#: What each working state does (``ctx`` is a :class:`cell.job.Context`).
STAGE_FUNCTIONS: dict[State, StageFunction] = {
    State.LOAD: load.run,
    State.PLAN: plan.run,
    State.VALIDATE: validate.run,
    State.ACQUIRE: acquire.run,
    State.MEASURE: measure.run,
    State.CALIBRATE: calibrate.run,
    State.ADJUST: adjust.run,
    State.CLOSE_LOOP: close_loop.run,
    State.REPORT: report.run,
}

if set(STAGE_FUNCTIONS) != set(STAGES):  # checked at import: the table and the stages agree
    raise RuntimeError(f"stage table out of step with the state table: {sorted(set(STAGES) ^ set(STAGE_FUNCTIONS))}")
