"""The ``cell`` command line.

Every command takes ``--json`` (one JSON document on stdout; human text on stderr).
Exit codes: 0 done, 1 the job faulted, 2 bad input, 130 aborted by the operator.
Errors are one line, never a traceback (set ``CELL_DEBUG=1`` to see one).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Callable

from calibration.errors import AbortRequested, CellError, InputError

EXIT_OK, EXIT_FAULT, EXIT_INPUT, EXIT_ABORT = 0, 1, 2, 130
UNITS = ("m", "mm", "cm", "um", "in", "ft")


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
    if args.what == "camera":
        from cell.measure_cmd import calibrate_camera_command

        args.images = args.cell_file
        return calibrate_camera_command(args, out)
    from cell.commands import calibrate

    return calibrate(args, out)


def cmd_serve(args, out: Output) -> int:
    from cell.web.serve import serve

    return serve(args, out)


def cmd_users(args, out: Output) -> int:
    from cell.web.serve import users

    return users(args, out)


def cmd_measure(args, out: Output) -> int:
    from cell.measure_cmd import measure_command

    return measure_command(args, out)


def cmd_detect(args, out: Output) -> int:
    from cell.detect_cmd import detect_command

    return detect_command(args, out)


def build_parser() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--json", action="store_true", help="print one JSON document on stdout")
    p = argparse.ArgumentParser(prog="cell", description="Robotic photogrammetric inspection cell", parents=[common])
    sub = p.add_subparsers(dest="command", required=True)

    c = sub.add_parser("check", parents=[common], help="validate a job (and a plan: dry run)")
    c.add_argument("job", type=Path)
    c.add_argument("--plan", type=Path, help="plan.json to validate against the robot and the cell")
    c.add_argument("--archive", type=Path, default=Path("archive"),
                   help="where the cell's calibration records are (a job naming a cell file: its calibration status)")
    c.set_defaults(func=cmd_check)

    c = sub.add_parser("plan", parents=[common], help="design the camera network only")
    c.add_argument("job", type=Path)
    c.add_argument("--out", type=Path, default=Path("plan.json"))
    c.add_argument("--png", type=Path, help="picture of the network (default: next to --out)")
    c.add_argument("--bound", action="store_true",
                   help="also prove how good any network could be (lower bound on the worst sigma; cheapest mode: "
                        "whether one station fewer could meet the requirement)")
    c.set_defaults(func=cmd_plan)

    url_help = "the archive database: sqlite:///PATH or postgresql://USER@HOST:PORT/DB (default: CELL_ARCHIVE_URL, " \
               "the cell file's [archive] url, else SQLite in the archive folder)"
    c = sub.add_parser("run", parents=[common], help="run a whole inspection job")
    c.add_argument("job", type=Path)
    c.add_argument("--archive", type=Path, default=Path("archive"))
    c.add_argument("--archive-url", help=url_help)
    c.add_argument("--backend", choices=["sim", "ur"], help="override the job file's [cell] backend")
    c.add_argument("--yes", action="store_true", help="confirm moving the robot without asking")
    c.add_argument("--serial", help="the part's serial number (goes into the report and the archive)")
    c.add_argument("--operator", help="who runs the job (default: the login name)")
    c.add_argument("--cell-id", help="this cell's id (default: $CELL_ID)")
    c.set_defaults(func=cmd_run)

    c = sub.add_parser("resume", parents=[common], help="resume a faulted or interrupted job")
    c.add_argument("job_id")
    c.add_argument("--archive", type=Path, default=Path("archive"))
    c.add_argument("--archive-url", help=url_help)
    c.add_argument("--yes", action="store_true", help="confirm resuming from the measured robot pose")
    c.add_argument("--operator", help="who resumes the job (default: the login name)")
    c.set_defaults(func=cmd_resume)

    c = sub.add_parser("locate", parents=[common], help="estimate where the part sits (base_from_part) from a few images")
    c.add_argument("job", type=Path)
    c.add_argument("--write", action="store_true", help="write the estimate into the job file's base_from_part")
    c.set_defaults(func=cmd_locate)

    c = sub.add_parser("calibrate", parents=[common],
                       help="calibrate the cell (hand-eye, reverify with a scale bar) or a camera from photographs")
    c.add_argument("what", choices=["hand-eye", "reverify", "camera"])
    c.add_argument("cell_file", type=Path, help="the cell file (CELL.toml); for 'camera' the folder of photographs")
    c.add_argument("--layout", type=Path, help="camera: the field's targets.csv (id,x,y,z,nx,ny,nz[,kind][,tolerance][,code])")
    c.add_argument("--camera", type=Path, help="camera: CAMERA.toml to start from (default: EXIF)")
    c.add_argument("--units", default="mm", choices=sorted(UNITS), help="camera: units of the layout (default mm)")
    c.add_argument("--out", type=Path, help="camera: the calibrated CAMERA.toml to write")
    c.add_argument("--control", type=Path, help="camera: control.csv: id,x,y,z[,sigma] of the field's certified "
                   "targets (sigma 0 or absent: held fixed); a flat field needs them")
    c.add_argument("--archive", type=Path, default=Path("archive"))
    c.add_argument("--backend", choices=["sim", "ur"], help="override the cell file's backend")
    c.add_argument("--yes", action="store_true", help="confirm moving the robot without asking")
    c.set_defaults(func=cmd_calibrate)

    c = sub.add_parser("measure", parents=[common], help="measure a folder of photographs: detect, identify, orient, bundle, report")
    c.add_argument("images", type=Path)
    c.add_argument("--camera", type=Path, help="CAMERA.toml (default: EXIF, polarity found per image, schneider14 codes)")
    c.add_argument("--layout", type=Path, help="targets.csv: nominal coordinates and codes (id,x,y,z,nx,ny,nz[,kind][,tolerance][,code])")
    c.add_argument("--control", type=Path, help="control.csv: id,x,y,z[,sigma] (sigma 0 or absent: held fixed)")
    c.add_argument("--units", default="mm", choices=sorted(UNITS), help="units of the layout and control files (default mm)")
    c.add_argument("--out", type=Path, required=True,
                   help="folder for measure.json, observations.csv, report.json, report.html")
    c.add_argument("--tolerance", type=float, default=0.5,
                   help="deviation from the layout allowed where the layout gives none (its units; default 0.5)")
    c.add_argument("--archive", type=Path, help="also file the measurement in this archive (like a job)")
    c.set_defaults(func=cmd_measure)

    c = sub.add_parser("detect", parents=[common], help="every detected centre of one image (dots and coded targets)")
    c.add_argument("image", type=Path)
    c.add_argument("--camera", type=Path, help="CAMERA.toml: polarity, coded-target family (default: found per image, schneider14)")
    c.add_argument("--png", type=Path, help="write the image with the detections drawn")
    c.add_argument("--polarity", choices=["auto", "bright", "dark"], help="override the camera file's polarity")
    c.add_argument("--family", help="override the camera file's coded_family (aruco, ring12, ring14, schneider12, "
                                    "schneider14, cct8, cct12)")
    c.set_defaults(func=cmd_detect)

    c = sub.add_parser("archive", parents=[common],
                       help="list, show, compare, verify archived jobs; sync the index; push a job to shared storage",
                       description="sync indexes every folder the index lacks or holds stale; a folder that does not "
                                   "match its manifest, a job the database refuses or another cell's job id is not "
                                   "indexed, named, and sync exits 1")
    c.add_argument("action", choices=["list", "show", "compare", "verify", "sync", "push"])
    c.add_argument("ids", nargs="*")
    c.add_argument("--repair", action="store_true",
                   help="with verify: close a job that ended without closing its folder (terminal record, manifest "
                        "over the files its journal vouches for); never vouches for a changed file")
    c.add_argument("--archive", type=Path, default=None, help="the job folders (default ./archive, or the folder of "
                   "a sqlite:/// archive url)")
    c.add_argument("--archive-url", help=url_help)
    for key in ("part", "serial", "verdict", "status", "since", "until", "cell-id"):
        c.add_argument(f"--{key}", help=f"list: only jobs with this {key}" if key not in ("since", "until") else
                       (f"list: jobs started {'at or after' if key == 'since' else 'before'} this ISO 8601 time or date; "
                        "a time without a zone (2026-11-23T08:13) is the cell's local time, as in job ids"
                        + ("; a date alone (2026-11-23) includes that whole day" if key == "until" else "")
                        + " (the console reads them the same way)"))
    c.add_argument("--adopt", action="store_true",
                   help="with sync: re-own the jobs the index holds from another path or host when the folder's "
                        "manifest is the indexed one (the archive moved, the host renamed); another cell's job is "
                        "never adopted")
    c.add_argument("--limit", type=int, default=None, help="list: at most this many jobs (newest first)")
    c.add_argument("--offset", type=int, default=0)
    c.add_argument("--to", help="push: the shared storage (a folder or s3://bucket/prefix; default CELL_ARCHIVE_PUSH)")
    c.set_defaults(func=cmd_archive)

    c = sub.add_parser("serve", parents=[common], help="the web console (operator screen, archive, JSON API)")
    c.add_argument("--host", default="127.0.0.1", help="address to listen on (default: this computer only). "
                   "X-Forwarded-For is not trusted unless CELL_TRUSTED_PROXY names the reverse proxy's address")
    c.add_argument("--port", type=int, default=8765)
    c.add_argument("--archive", type=Path, default=Path("archive"))
    c.add_argument("--programs", type=Path, default=Path("programs"),
                   help="folder of part programs: job files kept as templates (NAME.toml or NAME/job.toml)")
    c.add_argument("--archive-url", help=url_help + "; the jobs the console starts are indexed there too")
    c.add_argument("--cell-id", help="this cell's id (default: $CELL_ID)")
    c.add_argument("--certfile", type=Path, help="TLS certificate (PEM); with --keyfile the console speaks HTTPS only")
    c.add_argument("--keyfile", type=Path, help="TLS private key (PEM)")
    c.set_defaults(func=cmd_serve)

    c = sub.add_parser("users", parents=[common], help="console accounts: add (password on stdin), passwd, remove, list")
    c.add_argument("action", choices=["add", "passwd", "remove", "list"])
    c.add_argument("name", nargs="?")
    c.add_argument("--role", choices=["operator", "engineer", "admin"])
    c.add_argument("--archive", type=Path, default=Path("archive"))
    c.set_defaults(func=cmd_users)

    from cell.camera_cmd import add_camera_parser

    add_camera_parser(sub, common)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: usage errors are bad input
        return EXIT_INPUT if exc.code not in (0, None) else EXIT_OK
    out = Output(getattr(args, "json", False))
    # SIGTERM outside a job's own handling (which stops the robot first) ends a command as Ctrl-C does: exit 130
    if threading.current_thread() is threading.main_thread():
        old_term = signal.signal(signal.SIGTERM, _raise_abort)
    else:
        old_term = None
    try:
        return int(args.func(args, out))
    except (KeyboardInterrupt, AbortRequested):
        out.say("cell: aborted by the operator")
        if out.as_json:
            out.result({"status": "aborted"})
        return EXIT_ABORT
    except CellError as exc:
        code = EXIT_INPUT if isinstance(exc, InputError) else exc.exit_code
        return _error(out, type(exc).__name__, str(exc), code)
    except MemoryError:
        return _error(out, "MemoryError", "out of memory: the input is too large for this machine", EXIT_FAULT)
    except OSError as exc:  # disk full, read-only, a file where a folder should be: what and where
        where = f": {exc.filename}" if exc.filename else ""
        return _error(out, type(exc).__name__, f"{exc.strerror or exc}{where}", EXIT_FAULT)
    except Exception as exc:  # a bug: still one line (CELL_DEBUG=1 shows the traceback)
        return _error(out, type(exc).__name__, f"internal error {type(exc).__name__}: {exc} "
                      "(set CELL_DEBUG=1 for the traceback, and please report it)", EXIT_FAULT)
    finally:
        if old_term is not None:
            signal.signal(signal.SIGTERM, old_term)


def _raise_abort(signum, frame):
    raise AbortRequested(signal.Signals(signum).name)


def _error(out: Output, kind: str, message: str, code: int) -> int:
    out.say(f"cell: error: {message}")
    if out.as_json:
        out.result({"status": "error", "error": kind, "message": message, "exit_code": code})
    if os.environ.get("CELL_DEBUG"):
        raise
    return code


#: set by the console script (:func:`entry`): a one-shot process, whose loaded modules live until it ends
ONE_SHOT = False


def settle_loaded_modules() -> None:
    """In the console script, once a command has imported what it needs: move every object alive now (the
    modules, their classes and tables: ~10^6 objects) out of the garbage collector's full passes (``gc.freeze``).

    Each full pass otherwise walks all of them: 0.25 s per pass on this machine, three or more passes during a job
    (matplotlib's figures leave their cyclic garbage for it). The frozen objects are never collected, which costs
    nothing in a process that ends with the command; in-process callers (tests, the console's server) keep the
    ordinary collector. The collector, off while ``run``/``resume`` imported their modules, is turned on here.
    """
    if ONE_SHOT:
        import gc

        gc.freeze()
        gc.enable()  # off while the job's modules were imported (see entry)


def entry() -> None:
    """The ``cell`` console script: :func:`main`, then an exit that skips the interpreter's teardown.

    Tearing down the modules a job loads (trimesh, matplotlib, SQLAlchemy, scipy, ...) takes ~0.7-1 s on this
    machine after everything is written and closed: every result is fsync'ed and the run log and archive index are
    closed by then. So when only the main thread is left, the exit handlers run (logging's flush, ...), the
    standard streams are flushed and the process ends with ``os._exit``; with another thread still running the
    ordinary exit (which joins it) is taken.
    """
    global ONE_SHOT
    ONE_SHOT = True
    if sys.argv[1:2] in (["run"], ["resume"]):  # these settle their modules (settle_loaded_modules), which
        import gc  # turns the collector back on: importing them builds ~10^6 objects and no garbage worth

        gc.disable()  # three full passes (~0.4 s) on the way
    code = main()
    if threading.active_count() > 1:
        sys.exit(code)
    import atexit

    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed or broken pipe: nothing more to say
            pass
    os._exit(code)


if __name__ == "__main__":  # python -m cell.cli: run the importable module's entry (commands import cell.cli and
    from cell.cli import entry as _entry  # read its ONE_SHOT, not this __main__ copy's)

    _entry()
