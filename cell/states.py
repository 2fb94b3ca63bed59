"""The job's states and the table of allowed transitions (checked at import)."""
from __future__ import annotations

from enum import Enum


class State(str, Enum):
    CREATED = "CREATED"
    LOAD = "LOAD"
    PLAN = "PLAN"
    VALIDATE = "VALIDATE"
    ACQUIRE = "ACQUIRE"
    MEASURE = "MEASURE"
    CALIBRATE = "CALIBRATE"
    ADJUST = "ADJUST"
    CLOSE_LOOP = "CLOSE_LOOP"
    REPORT = "REPORT"
    DONE = "DONE"
    FAULTED = "FAULTED"
    ABORTED = "ABORTED"


#: The working stages, in order.
STAGES: tuple[State, ...] = (
    State.LOAD, State.PLAN, State.VALIDATE, State.ACQUIRE, State.MEASURE, State.CALIBRATE, State.ADJUST, State.CLOSE_LOOP,
    State.REPORT,
)
TERMINAL = frozenset({State.DONE, State.FAULTED, State.ABORTED})


def _table() -> dict[State, frozenset[State]]:
    t: dict[State, set[State]] = {s: set() for s in State}
    t[State.CREATED] = {State.LOAD}
    for a, b in zip(STAGES, STAGES[1:] + (State.DONE,)):
        t[a].add(b)
    for s in STAGES + (State.CREATED,):
        t[s] |= {State.FAULTED, State.ABORTED}
    # resume: a faulted or aborted job re-enters the stage it had not finished
    t[State.FAULTED] = set(STAGES)
    t[State.ABORTED] = set(STAGES)
    return {k: frozenset(v) for k, v in t.items()}


TRANSITIONS = _table()


class TransitionError(RuntimeError):
    """A transition the table does not allow: a bug in the cell, not an operator error."""


def check_transition(a: State, b: State) -> None:
    if b not in TRANSITIONS[a]:
        raise TransitionError(f"can't go from {a.value} to {b.value}")


def _check_table() -> None:
    for s in State:
        assert s in TRANSITIONS, s
    for s in TERMINAL - {State.FAULTED, State.ABORTED}:
        assert not TRANSITIONS[s], f"{s} is terminal"
    # every stage can reach DONE
    for s in STAGES:
        seen, todo = set(), [s]
        while todo:
            x = todo.pop()
            seen.add(x)
            todo += [y for y in TRANSITIONS[x] if y not in seen and y not in (State.FAULTED, State.ABORTED)]
        assert State.DONE in seen, s


_check_table()
