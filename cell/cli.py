"""The ``cell`` command line.

Every command takes ``--json`` (one JSON document on stdout; human text on stderr).
Exit codes: 0 done, 1 the job faulted, 2 bad input, 130 aborted by the operator.
Errors are one line, never a traceback (set ``CELL_DEBUG=1`` to see one).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Callable

from calibration.errors import AbortRequested, CellError, InputError

EXIT_OK, EXIT_FAULT, EXIT_INPUT, EXIT_ABORT = 0, 1, 2, 130


class Output:
    """Where a command speaks: human lines to stderr, one JSON document to stdout with ``--json``."""

    def __init__(self, as_json: bool):
        self.as_json = as_json

    def say(self, line: str = "") -> None:
        print(line, file=sys.stderr, flush=True)

    def progress(self, stage: str, fraction: float) -> None:
        """A one-line progress display on stderr (a bar on a terminal, plain lines otherwise)."""
        width = 30
        done = int(round(max(0.0, min(1.0, fraction)) * width))
        if sys.stderr.isatty():
            print(f"\r  {stage:<28} [{'#' * done}{'.' * (width - done)}] {fraction * 100:5.1f}%", end="", file=sys.stderr, flush=True)
            if fraction >= 1.0:
                print(file=sys.stderr, flush=True)
        elif fraction >= 1.0 or fraction == 0.0:
            print(f"  {stage}: {fraction * 100:.0f}%", file=sys.stderr, flush=True)

    def result(self, doc: dict, human: Callable[[dict], None] | None = None) -> None:
        if self.as_json:
            json.dump(doc, sys.stdout, indent=2, default=_json_default)
            sys.stdout.write("\n")
            sys.stdout.flush()
        if human is not None:
            human(doc)


def _json_default(o):
    import numpy as np

    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


# --- commands ------------------------------------------------------------------


def cmd_check(args, out: Output) -> int:
    from cell.commands import check

    return check(args, out)


def cmd_plan(args, out: Output) -> int:
    from cell.commands import plan

    return plan(args, out)


def cmd_run(args, out: Output) -> int:
    from cell.commands import run

    return run(args, out)


def cmd_resume(args, out: Output) -> int:
    from cell.commands import resume

    return resume(args, out)


def cmd_archive(args, out: Output) -> int:
    from cell.commands import archive

    return archive(args, out)


def cmd_locate(args, out: Output) -> int:
    from cell.cellcal.locate import locate_part

    doc = locate_part(args.job, out, write=args.write)
    out.result(doc)
    return 0


def cmd_calibrate(args, out: Output) -> int:
    from cell.commands import calibrate

    return calibrate(args, out)


def build_parser() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--json", action="store_true", help="print one JSON document on stdout")
    p = argparse.ArgumentParser(prog="cell", description="Robotic photogrammetric inspection cell", parents=[common])
    sub = p.add_subparsers(dest="command", required=True)

    c = sub.add_parser("check", parents=[common], help="validate a job (and a plan: dry run)")
    c.add_argument("job", type=Path)
    c.add_argument("--plan", type=Path, help="plan.json to validate against the robot and the cell")
    c.set_defaults(func=cmd_check)

    c = sub.add_parser("plan", parents=[common], help="design the camera network only")
    c.add_argument("job", type=Path)
    c.add_argument("--out", type=Path, default=Path("plan.json"))
    c.add_argument("--png", type=Path, help="picture of the network (default: next to --out)")
    c.add_argument("--bound", action="store_true",
                   help="also prove how good any network could be (lower bound on the worst sigma; cheapest mode: "
                        "whether one station fewer could meet the requirement)")
    c.set_defaults(func=cmd_plan)

    c = sub.add_parser("run", parents=[common], help="run a whole inspection job")
    c.add_argument("job", type=Path)
    c.add_argument("--archive", type=Path, default=Path("archive"))
    c.add_argument("--backend", choices=["sim", "ur"], help="override the job file's [cell] backend")
    c.add_argument("--yes", action="store_true", help="confirm moving the robot without asking")
    c.set_defaults(func=cmd_run)

    c = sub.add_parser("resume", parents=[common], help="resume a faulted or interrupted job")
    c.add_argument("job_id")
    c.add_argument("--archive", type=Path, default=Path("archive"))
    c.add_argument("--yes", action="store_true", help="confirm resuming from the measured robot pose")
    c.set_defaults(func=cmd_resume)

    c = sub.add_parser("locate", parents=[common], help="estimate where the part sits (base_from_part) from a few images")
    c.add_argument("job", type=Path)
    c.add_argument("--write", action="store_true", help="write the estimate into the job file's base_from_part")
    c.set_defaults(func=cmd_locate)

    c = sub.add_parser("calibrate", parents=[common], help="calibrate the cell: hand-eye, or reverify with a scale bar")
    c.add_argument("what", choices=["hand-eye", "reverify"])
    c.add_argument("cell_file", type=Path, help="the cell file (CELL.toml)")
    c.add_argument("--archive", type=Path, default=Path("archive"))
    c.add_argument("--backend", choices=["sim", "ur"], help="override the cell file's backend")
    c.add_argument("--yes", action="store_true", help="confirm moving the robot without asking")
    c.set_defaults(func=cmd_calibrate)

    c = sub.add_parser("archive", parents=[common], help="list, show, compare, verify archived jobs")
    c.add_argument("action", choices=["list", "show", "compare", "verify"])
    c.add_argument("ids", nargs="*")
    c.add_argument("--archive", type=Path, default=Path("archive"))
    c.set_defaults(func=cmd_archive)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: usage errors are bad input
        return EXIT_INPUT if exc.code not in (0, None) else EXIT_OK
    out = Output(getattr(args, "json", False))
    try:
        return int(args.func(args, out))
    except (KeyboardInterrupt, AbortRequested):
        out.say("cell: aborted by the operator")
        if out.as_json:
            out.result({"status": "aborted"})
        return EXIT_ABORT
    except CellError as exc:
        code = EXIT_INPUT if isinstance(exc, InputError) else exc.exit_code
        out.say(f"cell: error: {exc}")
        if out.as_json:
            out.result({"status": "error", "error": type(exc).__name__, "message": str(exc), "exit_code": code})
        if os.environ.get("CELL_DEBUG"):
            raise
        return code


if __name__ == "__main__":
    sys.exit(main())
