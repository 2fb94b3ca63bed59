"""Re-export of the cell's error hierarchy (defined in ``calibration.errors``)."""
from calibration.errors import *  # noqa: F401,F403
from calibration.errors import __dict__ as _d

__all__ = [k for k, v in _d.items() if isinstance(v, type) and issubclass(v, BaseException)]
