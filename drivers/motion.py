"""Did the arm move? One test and one tolerance for the UR driver, its client process and the cell.

Three places ask it: the ur-rtde client process (:mod:`drivers.ur_worker`: the arm moved while the controller
checked a target), the driver (:mod:`drivers.ur`: a refusal only with the arm where the move started) and the
cell (:mod:`cell.stages.exposure`: the arm moved during the exposure; :mod:`cell.stages.acquire`: a refused
station is skipped only when the arm stayed put). Pure Python, no numpy: the client process imports it too.
"""
from __future__ import annotations

import math
from collections.abc import Iterable

#: The arm moved when some joint reads further than this (rad) from the reference reading. A UR's joint
#: readings at rest scatter by ~1e-5 rad (encoder noise): ten times that is never a still arm called moving,
#: and far below any motion of the arm (a move, a sway, a protective stop's braking).
MOVED_TOL_RAD = 1e-4


def joint_change_rad(before: Iterable[float], after: Iterable[float]) -> float:
    """The largest joint change (rad) between two readings; ``inf`` when a value of either is not finite (a reading
    that cannot show the arm still). ``ValueError`` when they are not the same length or are empty."""
    a, b = [float(v) for v in before], [float(v) for v in after]
    if len(a) != len(b) or not a:
        raise ValueError(f"joint readings of {len(a)} and {len(b)} values: cannot compare them")
    if not all(math.isfinite(v) for v in a + b):  # max() would skip a NaN, depending on where it stands
        return math.inf
    return max(abs(x - y) for x, y in zip(a, b))


def arm_moved(before: Iterable[float], after: Iterable[float], tol_rad: float = MOVED_TOL_RAD) -> bool:
    """True when some joint changed by more than ``tol_rad`` between the readings ``before`` and ``after`` (or a
    value is not finite); a change of exactly ``tol_rad`` is still."""
    return joint_change_rad(before, after) > tol_rad


def describe_change(change_rad: float) -> str:
    """``joint_change_rad``'s value for a message: "0.00012 rad", or what a non-finite reading means."""
    return f"{change_rad:.5f} rad" if math.isfinite(change_rad) else "an unknown amount (a joint reading is not finite)"
