"""cell: the job state machine, CLI, run log, report and archive."""

__version__ = "0.1.0"
