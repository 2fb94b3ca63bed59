"""The error hierarchy of the cell: one base error, one subclass per layer.

It lives in the bottom package (``calibration`` imports nothing of ours) so every
layer can raise its own subclass; ``cell.errors`` re-exports it for the CLI.
Messages say what went wrong, where, and what to do.
"""
from __future__ import annotations


class CellError(Exception):
    """Base of every error the cell raises on purpose."""

    exit_code = 1


class InputError(CellError):
    """Bad input given by the user (files, options): the CLI exits 2."""

    exit_code = 2


class JobSpecError(InputError):
    """The job file is missing, malformed, or inconsistent."""


class PartError(InputError):
    """The CAD mesh or the targets file cannot be used."""


class PlanningError(CellError):
    """Network design failed (no valid network, data insufficient)."""


class ReachabilityError(PlanningError):
    """A station cannot be reached by the robot, or a move collides."""

    exit_code = 2


class DriverError(CellError):
    """Hardware (or its simulation) failed."""


class NotConnectedError(DriverError):
    """The device is not connected or the connection dropped."""


class MotionError(DriverError):
    """A motion was refused, failed, or timed out."""


class MoveRefusedError(MotionError):
    """The controller refused a move before the arm moved (the target cannot be reached from here)."""


class ProtectiveStopError(MotionError):
    """The robot controller entered a protective or emergency stop."""


class LimitError(MotionError):
    """A command exceeds the cell's own speed, acceleration or workspace limits.

    Raised before anything is sent to the hardware.
    """


class CalibrationError(CellError):
    """Camera calibration, measurement, or bundle adjustment failed."""


class ScaleNotEstablishedError(CalibrationError):
    """No scale bar keeps both ends observed in two images or more (e.g. data snooping rejected an end's rays):
    the network has no scale of its own. ``ends`` {target index: usable rays}, ``rejected`` (observation
    indices data snooping had rejected of those ends); a caller may adjust a free network and say so."""

    def __init__(self, message: str, ends: dict | None = None, rejected: list | None = None):
        super().__init__(message)
        self.ends = dict(ends or {})
        self.rejected = list(rejected or [])


class RecordError(CellError):
    """A job's record (journal, stored files, manifest) is damaged or cannot be written.

    The job is not driven on such a record: the message names the file (and line) and what to do.
    """


class AbortRequested(Exception):
    """The operator asked to stop (Ctrl-C, SIGTERM). A signal, not a failure."""
