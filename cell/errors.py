"""Re-export of the cell's error hierarchy (defined in ``calibration.errors``, docs/decisions/0002)."""
from calibration.errors import (AbortRequested, CalibrationError, CellError, DriverError, InputError, JobSpecError,
                                LimitError, MotionError, NotConnectedError, PartError, PlanningError,
                                ProtectiveStopError, ReachabilityError)

__all__ = ["AbortRequested", "CalibrationError", "CellError", "DriverError", "InputError", "JobSpecError",
           "LimitError", "MotionError", "NotConnectedError", "PartError", "PlanningError", "ProtectiveStopError",
           "ReachabilityError"]
