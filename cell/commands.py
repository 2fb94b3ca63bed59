"""The CLI's commands, each a thin layer over the packages below."""
from __future__ import annotations

from calibration.errors import CellError


def _human_check(doc: dict, out) -> None:
    p = doc["part"]
    m = p["mesh"]
    size = " x ".join(f"{v * 1000:.1f}" for v in p["size_m"])
    out.say(f"job    {doc['job']['name']}  ({doc['job']['file']}, units {doc['job']['units']}, seed {doc['job']['seed']})")
    out.say(f"part   {p['name']}: {size} mm, {m['faces']} faces, watertight={m['watertight']}, "
            f"winding consistent={m['winding_consistent']}, degenerate faces={m['degenerate_faces']}")
    kinds = ", ".join(f"{v} {k}" for k, v in p["targets_by_kind"].items())
    out.say(f"targets {p['targets']} ({kinds}), dot {p['target_diameter_m'] * 1000:.1f} mm, code {p['coded_size_m'] * 1000:.1f} mm")
    c = doc["camera"]
    out.say(f"camera {c['width']} x {c['height']} px, f = {c['fx_px']:.1f} px, sigma {c['sigma_px']} px")
    out.say(f"cell   {doc['cell']['robot']} ({doc['cell']['backend']}), {doc['cell']['obstacles']} obstacle(s)")
    if "plan" in doc:
        pl = doc["plan"]
        out.say(f"plan   {pl['stations']} stations reachable and collision-free; cycle time {pl['cycle_time_s']:.1f} s")
    out.say("check  OK")


def check(args, out) -> int:
    from cell.load import load

    job = load(args.job)
    doc = {"status": "ok"} | job.summary()
    if args.plan is not None:
        from cell.validate import validate_plan_file

        doc["plan"] = validate_plan_file(job, args.plan)
    out.result(doc, lambda d: _human_check(d, out))
    return 0


def _not_yet(name: str):
    raise CellError(f"'cell {name}' is not available in this build yet")


def plan(args, out) -> int:
    _not_yet("plan")


def run(args, out) -> int:
    _not_yet("run")


def resume(args, out) -> int:
    _not_yet("resume")


def archive(args, out) -> int:
    _not_yet("archive")
