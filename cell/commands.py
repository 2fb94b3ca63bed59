"""The CLI's commands, each a thin layer over the packages below."""
from __future__ import annotations

import json
from pathlib import Path

from calibration.errors import CellError


def _human_check(doc: dict, out) -> None:
    p = doc["part"]
    m = p["mesh"]
    size = " x ".join(f"{v * 1000:.1f}" for v in p["size_m"])
    out.say(f"job    {doc['job']['name']}  ({doc['job']['file']}, units {doc['job']['units']}, seed {doc['job']['seed']})")
    bodies = f", {m['bodies']} bod{'y' if m['bodies'] == 1 else 'ies'}" if "bodies" in m else ""
    out.say(f"part   {p['name']}: {size} mm, {m['faces']} faces{bodies}, watertight={m['watertight']}, "
            f"winding consistent={m['winding_consistent']}, degenerate faces={m['degenerate_faces']}")
    from planning.part import mesh_warnings

    for w in mesh_warnings(m):  # open, faces twice, non-manifold, bodies on each other, faces flipped (decision 0068)
        out.say(f"part   WARNING {w}")
    if p.get("normals_warning"):
        out.say(f"targets WARNING {p['normals_warning']}")
    if (p.get("symmetry") or {}).get("warning"):  # decision 0058: a placement one step off names dots wrongly
        out.say(f"targets WARNING {p['symmetry']['warning']}")
    kinds = ", ".join(f"{v} {k}" for k, v in p["targets_by_kind"].items())
    th = doc.get("target_thickness_m")
    thick = "" if th is None else f", {th * 1000:.2f} mm thick"
    out.say(f"targets {p['targets']} ({kinds}), dot {p['target_diameter_m'] * 1000:.1f} mm{thick}, "
            f"code {p['coded_size_m'] * 1000:.1f} mm")
    c = doc["camera"]
    weights = c.get("observation_weights")
    said = (f"image sigma from the detector model; {c['sigma_px']} px for the network search ([camera] sigma_px)"
            if weights == "model" else f"image sigma {c['sigma_px']} px ({weights} weights)")
    out.say(f"camera {c['width']} x {c['height']} px, f = {c['fx_px']:.1f} px, {said}")
    out.say(f"cell   {doc['cell']['robot']} ({doc['cell']['backend']}), {doc['cell']['obstacles']} obstacle(s)")
    if doc["cell"].get("taken_from_cell_file"):  # the cell's hand-eye and lens (decision 0056)
        from cell.cellcal.jobcell import taken_line

        taken = doc["cell"]["taken_from_cell_file"]
        out.say(f"cell   {taken_line(taken)}" + ("" if taken["hand_eye"]["calibrated"] else
                                                 ": WARNING run `cell calibrate hand-eye` first"))
        if (doc.get("cell_calibration") or {}).get("status") == "verified":
            out.say(f"cell   calibration verified: {doc['cell_calibration']['detail']}")
    if doc.get("target_thickness_note"):
        out.say(f"targets WARNING {doc['target_thickness_note']}")
    r = doc.get("measurability")
    if r and r["unmeasurable"]:
        for w in doc.get("warnings", []):
            out.say(f"reach  WARNING {w}")
    elif r:
        out.say(f"reach  every target seen by >= {r['min_rays']} of {r['reachable']} reachable candidate stations "
                f"({r['candidates']} on the viewing sphere)")
    for b in (r or {}).get("scale_bars") or []:
        out.say(f"bar    scale bar {'-'.join(b['ends'])}: ends seen by {b['candidates'][0]} / {b['candidates'][1]} "
                f"reachable candidate stations well inside the image, 10 deg below the incidence limit")
        if b.get("warning"):
            out.say(f"bar    WARNING {b['warning']}")
    if "plan" in doc:
        pl = doc["plan"]
        out.say(f"plan   {pl['stations']} stations reachable and collision-free; cycle time {pl['cycle_time_s']:.1f} s")
    out.say("check  OK")


def check(args, out) -> int:
    from cell.loadedjob import load

    job = load(args.job)
    doc = {"status": "ok"} | job.summary()
    if job.cell is not None:  # as `cell run` judges it: a cell whose reverification failed measures no part
        from cell.job import check_cell_calibration

        st = check_cell_calibration(job, getattr(args, "archive", None) or Path("archive"), out)
        doc["cell_calibration"] = {k: st.get(k) for k in ("status", "detail")}
    from calibration.errors import JobSpecError
    from cell.stages.plan import unmeasurable_targets

    reach = unmeasurable_targets(job)
    doc["measurability"] = reach
    bars = reach.get("scale_bars") or []
    if reach["unmeasurable"]:
        bad = reach["unmeasurable"]
        on_bar = [t for t in bad if any(t in b["ends"] for b in bars)]
        hit = ["-".join(b["ends"]) for b in bars if any(t in b["ends"] for t in bad)]
        what = (f"{len(bad)} target(s) cannot be seen by [planning] min_rays = {reach['min_rays']} reachable "
                f"stations (e.g. " + ", ".join(f"{t}: {reach['rays'][t]}" for t in (on_bar + bad)[:5]) + ")"
                + (f", among them the end(s) {', '.join(on_bar)} of the scale bar{'s' if len(hit) > 1 else ''} "
                   f"{', '.join(hit)}: "
                   + ("the scale cannot be established" if len(hit) == len(bars) else "those bars cannot be used")
                   if on_bar else ""))
        none = reach.get("buried") or []
        if none:  # no placement of the part helps these: say what does
            size = max(doc["part"]["size_m"]) * 1000
            what += (f"; {len(none)} of them ({', '.join(none[:3])}{', ...' if len(none) > 3 else ''}) are covered by "
                     "the part's own surface along their normal: check that they lie on the surface with outward "
                     f"normals and that the units are right (the part is {size:.1f} mm across in {doc['job']['units']})")
            m = doc["part"]["mesh"]
            if m.get("duplicate_faces"):  # a second body on the first covers its targets (decision 0068)
                what += f"; the mesh gives {m['duplicate_faces']} faces twice (the part exported twice?)"
            elif m.get("bodies", 1) > 1:
                pair = m.get("overlapping_bodies") or []
                what += (f"; the mesh holds {m['bodies']} bodies" + (f", {pair[0][0]} and {pair[0][1]} overlapping (the "
                         "part given twice?)" if pair else "") + ": a second body may be what covers them")
        else:
            from planning.part import units_hint

            what += units_hint(max(doc["part"]["size_m"]), doc["job"]["units"])
        if job.spec.planning.unmeasurable != "report":
            act = ("correct the targets file or the units" if len(none) == len(bad) else
                   "lower [planning] min_rays, raise [planning] incidence_max_deg, widen [planning] elevation_min_deg / "
                   "elevation_max_deg, move the part ([cell] base_from_part)")
            raise JobSpecError(f'{job.path}: {what}: {act}, or set [planning] unmeasurable = "report" to measure the '
                               "others and report these not measured")
        doc["warnings"] = [f"{what}: they will be reported not measured ([planning] unmeasurable = \"report\")"]
    for bar in bars:
        weak = [f"{t} ({n})" for t, n in zip(bar["ends"], bar["candidates"]) if n < bar["rays_min"]]
        if weak:  # a warning, not an error: PLAN says what it achieves for the bar (planning/scalebar.py)
            bar["warning"] = (
                f"scale bar {'-'.join(bar['ends'])}: end(s) {', '.join(weak)} seen by fewer than "
                f"{bar['rays_min']} (2 x min_rays) reachable candidate stations with a sure view (well inside the "
                "image, 10 deg below the incidence limit): the scale rests on few rays; "
                "choose ends the robot sees from more directions, or widen [planning] elevation_min_deg / "
                "elevation_max_deg, incidence_max_deg")
    from cell.stages.report import thickness_doc

    note = thickness_doc(job, job.spec.cell.backend).get("note")
    if note:  # a real cell's targets have a thickness: said before the job, as the report will say it after
        doc["target_thickness_note"] = note
    if args.plan is not None:
        from cell.stages.validate import validate_plan_file

        doc["plan"] = validate_plan_file(job, args.plan)
    out.result(doc, lambda d: _human_check(d, out))
    return 0


def _check_writable(what: str, path: Path) -> None:
    """InputError (one line) when ``path`` cannot become a file: a folder, under a file, or in a folder not writable."""
    import os

    from calibration.errors import InputError

    if path.is_dir():
        raise InputError(f"{path}: {what} names a folder; give a file name (e.g. {path / 'plan.json'})")
    parent = next((a for a in path.absolute().parents if a.exists()), None)
    if parent is not None and not parent.is_dir():
        raise InputError(f"{path}: {what}: {parent} is a file, not a folder")
    if parent is not None and not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"{path}: {what}: the folder {parent} is not writable")


def plan(args, out) -> int:
    from cell.record.jobfolder import atomic_write_json
    from cell.loadedjob import load
    from cell.stages.plan import make_plan

    png = args.png or args.out.with_suffix(".png")
    for what, path in (("--out", args.out), ("--png", png)):  # before planning: nothing written when they cannot be
        _check_writable(what, Path(path))
    job = load(args.job)
    out.say(f"planning {job.part.name}: {len(job.part.targets)} targets, mode {job.spec.planning.mode}")
    p, facts = make_plan(job, progress=out.progress, lower_bound=True if args.bound else None)
    doc = p.to_plan_dict() | {"databases": facts}
    atomic_write_json(args.out, doc)
    from planning.plot import plot_plan

    plot_plan(job.part, p, png)
    summary = {"status": "ok", "plan": str(args.out), "picture": str(png), "stations": len(p.station_ids),
               "predicted_sigma_max_m": p.predicted_sigma_max_m, "predicted_sigma_mean_m": p.predicted_sigma_mean_m,
               "timing": p.timing, "databases": facts,
               **{k: v for k, v in p.search.items() if k.startswith(("lower_bound", "plan_over", "fewer_stations"))}}
    if p.scale_bars:
        from planning.scalebar import bar_warnings

        summary["scale_bars"] = p.scale_bars
        summary["scale_bar_lines"] = [w for d in p.scale_bars for w in bar_warnings(d)]

    def human(d):
        out.say(f"plan   {d['stations']} stations, predicted sigma max {d['predicted_sigma_max_m'] * 1e6:.1f} um, "
                f"mean {d['predicted_sigma_mean_m'] * 1e6:.1f} um -> {d['plan']} (picture {d['picture']})")
        if "lower_bound_sigma_m" in d:
            r = d["plan_over_lower_bound"]
            how = ("within {:.0%} of it".format(r - 1) if r >= 1 else
                   "below it: the polish moved stations off the database's lattice")
            n_bar = sum(len(b.get("stations_added") or []) for b in d.get("scale_bars") or [])
            out.say(f"bound  no {d['stations'] - n_bar}-station network made of the {facts['candidates']} database "
                    f"candidates gets its worst target below {d['lower_bound_sigma_m'] * 1e6:.1f} um; the "
                    f"{'search' + chr(39) + 's ' if n_bar else ''}plan is {how}"
                    + (f" ({n_bar} station(s) added for the scale bar(s) after it)" if n_bar else ""))
        for level, line in d.get("scale_bar_lines", []):
            out.say(f"{'WARNING ' if level == 'warning' else 'bar    '}{line}")
        if "fewer_stations" in d:
            verdict = ("cannot" if d["fewer_stations_cannot_meet"] else "might")
            out.say(f"bound  {d['fewer_stations']} stations {verdict} meet the required precision "
                    f"(lower bound on sigma / required: {d['fewer_stations_lower_bound_ratio']:.2f})")

    out.result(summary, human)
    return 0


def _confirm(args, out, what: str) -> None:
    """Moving a real robot (or resuming) needs the operator's yes."""
    import sys

    from calibration.errors import InputError

    if args.yes:
        return
    if sys.stdin.isatty():
        answer = input(f"{what} Type 'yes' to go on: ").strip().lower()
        if answer == "yes":
            return
    raise InputError(f"{what} Confirm with --yes.")


def _finish(result, out) -> int:
    from cell.states import State

    doc = {"status": result.status.value, "job_id": result.job_id, "folder": str(result.folder),
           "reason": result.reason, "stage_times_s": result.stage_times_s}
    rep = result.folder / "report.html"
    if result.status == State.DONE:
        doc["report"] = str(rep)
        try:
            doc["verdict"] = json.loads((result.folder / "report.json").read_text())["verdict"]
        except (OSError, KeyError, ValueError):
            pass
    def human(d):
        line = f"job {d['job_id']}  {d['status']}"
        if d["status"] == "DONE":
            line += f"  {d.get('verdict', '')}  report: {d['report']}"
        else:
            line += f"  {d['reason']}"
        out.say(line)
    out.result(doc, human)
    return result.exit_code


def run(args, out) -> int:
    from cell.cli import settle_loaded_modules
    from cell.job import start_job

    settle_loaded_modules()

    backend = args.backend
    if (backend or "") == "ur":
        _confirm(args, out, "This job moves the robot.")
    return _finish(start_job(args.job, args.archive, backend, out, serial=args.serial,
                             operator=args.operator or _login_name(), cell_id=args.cell_id,
                             archive_url=args.archive_url), out)


def _login_name() -> str | None:
    import getpass

    try:
        return getpass.getuser()
    except (KeyError, OSError):  # no name for this uid (containers)
        return None


def resume(args, out) -> int:
    from cell.cli import settle_loaded_modules
    from cell.job import resume_job

    settle_loaded_modules()

    _confirm(args, out, f"Resuming {args.job_id} moves the robot from its measured pose.")
    return _finish(resume_job(args.job_id, args.archive, out, operator=args.operator or _login_name(),
                              archive_url=args.archive_url), out)


def _open_archive(args):
    """``--archive`` / ``--archive-url`` of ``cell archive``: the folders and the index."""
    import os
    from pathlib import Path

    from cell.record.archive import Archive, check_archive_root, resolve_url

    url = resolve_url(args.archive_url, args.archive or Path("archive"))
    root = args.archive
    if root is None:  # a sqlite:/// url names its folder; otherwise ./archive
        root = Path(url[len("sqlite:///"):]).parent if url.startswith("sqlite:///") else Path("archive")
    if args.action == "verify" and not Path(root).is_dir():  # a typo must not verify an empty
        from calibration.errors import InputError  # archive it creates (an outside check: "index matches", exit 0)

        raise InputError(f"{root}: no archive folder here; give --archive the folder that holds the jobs")
    return Archive(check_archive_root(root, write=False), url, push=args.to or os.environ.get("CELL_ARCHIVE_PUSH"))


def archive(args, out) -> int:
    from calibration.errors import InputError

    from cell.record.archive import scrub

    a = _open_archive(args)
    try:
        return _archive_action(a, args, out)
    except CellError as exc:  # one line, never a password (a url in a driver's message, a libpq ?password=)
        exc.args = (scrub(exc, a.url), *exc.args[1:])
        raise
    finally:
        for line in a.messages:
            out.say(f"archive: {scrub(line, a.url)}")
        a.close()


def _archive_action(a, args, out) -> int:
    from pathlib import Path

    from calibration.errors import CellError
    from calibration.errors import InputError
    from cell.record.archive import INCOMING, check_job_id

    if getattr(args, "repair", False) and not (args.action == "verify" and args.ids):
        raise InputError("--repair goes with 'cell archive verify ID'")
    if args.action == "list":
        from cell.record.archive import user_time

        filters = {k: getattr(args, k) for k in ("part", "serial", "verdict", "status", "since", "until", "cell_id")}
        # one rule with the console: no zone is the cell's local time; --until DATE is that whole day
        for k in ("since", "until"):
            if filters[k] is not None:
                try:
                    filters[k] = user_time(filters[k], end=k == "until")
                except InputError as exc:
                    raise InputError(f"--{k}: {exc}") from None
        url = a.url
        if url.startswith("sqlite:///") and not Path(url[len("sqlite:///"):]).exists() and not a.root.is_dir():
            rows, total = [], 0  # no archive here yet: nothing to list, nothing created
        else:
            if a.root.is_dir():
                a.catch_up()  # folders the index does not hold yet (copied in, or indexed elsewhere)
            rows = a.index.list_jobs(**filters, limit=args.limit, offset=args.offset,
                                     newest_first=args.limit is not None)
            total = a.index.count_jobs(**filters)
            missing = a.index.not_measured_counts([r["id"] for r in rows if r.get("targets") is not None])
            for r in rows:
                r["staged"] = False
                # failed: measured and beyond tolerance; not measured apart (a target not measured did not fail)
                r["not_measured"] = missing.get(r["id"], 0) if r.get("targets") is not None else None
                if r.get("problem") is None:
                    r.pop("problem", None)
            if args.offset == 0 and not any(v is not None for v in filters.values()):
                rows += a.staged_rows()
        doc = {"archive": a.shown_url, "total": total, "jobs": rows,
               "outbox": a.outbox.pending()}
        def human(d):
            for r in d["jobs"]:
                status = r["status"] + (" (staged: stopped before ACQUIRE; 'cell resume' goes on)" if r.get("staged")
                                        else "")
                out.say(f"{r['id']:<40} {status:<9} {r.get('verdict') or '':<10} "
                        f"{(r.get('failed') if r.get('failed') is not None else ''):>4} failed of {r.get('targets') or '?'}"
                        + (f", {r['not_measured']} not measured" if r.get("not_measured") else "")
                        + (f"  ! {r['problem']}" if r.get("problem") else ""))
            if not d["jobs"]:
                out.say(f"no jobs in {d['archive']}")
            if d["outbox"]:
                out.say(f"{len(d['outbox'])} job(s) wait in the outbox for the database: run 'cell archive sync'")
        out.result(doc, human)
        return 0
    if args.action == "show":
        if len(args.ids) != 1:
            raise InputError("cell archive show takes one job id")
        job_id = check_job_id(args.ids[0])
        if (a.root / job_id).exists() or (a.root / INCOMING / job_id).exists() or (a.root / job_id).is_symlink():
            doc = a.show(job_id)
        else:  # another cell's job: what the index holds
            row = a.index.get_job(job_id)
            if row is None:
                raise InputError(f"{a.index.url}: no job {job_id!r} in the archive (see 'cell archive list')")
            tl = a.index.job_targets(job_id)
            # failed: measured and beyond tolerance (an index row of a target not measured has no deviation)
            doc = {"id": job_id, "folder": row["folder"], "origin": row["origin"], "verdict": row["verdict"],
                   "sigma0_px": row["sigma0_px"], "targets": len(tl),
                   "failed": [t["id"] for t in tl if t["deviation_norm_m"] is not None and t["pass"] is False],
                   "not_measured": [t["id"] for t in tl if t["deviation_norm_m"] is None],
                   "undecided": [t["id"] for t in tl if t["deviation_norm_m"] is not None
                                 and (t["decision"] in ("inconclusive", "undecided") or row["verdict"] == "UNTRUSTED")],
                   "index": row}
        out.result(doc, lambda d: out.say(json.dumps(d, indent=1, default=str)))
        return 0
    if args.action == "compare":
        for j in args.ids:  # another cell's job: the index holds it, but compare reads this cell's folders
            check_job_id(j)
            if not ((a.root / j).exists() or (a.root / INCOMING / j).exists()):
                try:
                    row = a.index.get_job(j)
                except CellError:
                    row = None
                if row is not None and row.get("origin") != a.origin:
                    raise InputError(f"{j}: another cell's job (from {row['origin']}): 'cell archive compare' reads "
                                     f"this cell's job folders only; run it on that cell ('cell archive show {j}' "
                                     "shows what the index holds)")
        doc = a.compare(args.ids)
        def human(d):
            if d.get("note"):
                out.say(f"WARNING {d['note']}")
            out.say(f"part {d['part']}: {len(d['targets'])} targets in {len(d['jobs'])} jobs; "
                    f"{len(d['drifting'])} drift beyond 3 sigma: {', '.join(d['drifting'][:20])}")
            if d.get("not_measured"):
                out.say(f"{len(d['not_measured'])} target(s) not measured in every job (no drift where the first or "
                        "last did not measure it): " + "; ".join(f"{m['id']} in {', '.join(m['jobs'])}"
                                                                for m in d["not_measured"][:10])
                        + (" ..." if len(d["not_measured"]) > 10 else ""))
            for r in d["targets"]:
                if r["drift_significant"] or any(p is False for p in r["pass"]) or None in r["pass"]:
                    drift = "--" if r["drift_m"] is None else f"{r['drift_m'] * 1e6:.1f} um"
                    if r.get("drift_sigma_m") is not None:
                        drift += f" (sigma {r['drift_sigma_m'] * 1e6:.1f} um)"
                    out.say(f"  {r['id']:<8} |d| um " + " ".join("   --  " if v is None else f"{v * 1e6:7.1f}"
                                                                 for v in r["deviation_norm_m"]) + f"  drift {drift}")
        out.result(doc, human)
        return 0
    if args.action == "verify":
        if not args.ids:  # the index against the folders
            doc = a.verify_index()
            def human(d):
                out.say(f"{d['checked']} job folders, {d['indexed']} indexed, {len(d['outbox'])} in the outbox: "
                        + (f"{len(d['problems'])} problem(s)" if d["problems"] else "index matches the folders"))
                for p in d["problems"]:
                    out.say(f"  {p}")
                for p in d["damaged"]:
                    out.say(f"  {p} (a damaged folder: 'cell archive verify ID' says more)")
                if d["unclosed"]:
                    out.say(f"{len(d['unclosed'])} job(s) never closed:")
                for p in d["unclosed"] + d["running"]:
                    out.say(f"  {p}")
            out.result(doc, human)
            return 0 if doc["intact"] else 1
        if len(args.ids) != 1:
            raise InputError("cell archive verify takes one job id (or none: the index against the folders)")
        repaired = None
        if args.repair:
            from cell.job import repair_job

            repaired = repair_job(a, args.ids[0])
            out.say(f"{args.ids[0]}: {repaired}")
        problems = a.verify(args.ids[0])
        doc = {"job_id": args.ids[0], "intact": not problems, "problems": problems}
        if repaired is not None:
            doc["repaired"] = repaired
        out.result(doc, lambda d: out.say(f"{d['job_id']}: " + ("manifest intact" if d["intact"] else
                                                              "; ".join(d["problems"]))))
        return 0 if not problems else 1
    if args.action == "sync":
        doc = a.sync(adopt=args.adopt)
        def human(d):
            out.say(f"drained {len(d['drained'])} from the outbox, indexed {len(d['indexed'])} more, "
                    f"{len(d['pending'])} still waiting; pushed {len(d['pushed'])}, {len(d['push_pending'])} pushes waiting")
            for e in d["adopted"]:
                out.say(f"  adopted {e['id']}: the same job (its manifest) indexed from {e['from']}")
            for e in d["problems"]:
                out.say(f"  {e} (indexed as far as it reads)")
            for e in d["skipped"]:
                out.say(f"  NOT INDEXED {e['id']}: {e['reason']}")
            if d["skipped"]:
                out.say(f"sync: {len(d['skipped'])} job(s) not indexed: {', '.join(e['id'] for e in d['skipped'])}")
        out.result(doc, human)
        return 0 if not doc["pending"] and not doc["push_pending"] and not doc["skipped"] else 1
    if args.action == "push":
        if not args.ids:
            raise InputError("cell archive push takes one or more job ids")
        docs = [a.push(j) for j in args.ids]
        out.result({"pushed": docs}, lambda d: [out.say(f"{x['job_id']} -> {x['dest']}: {x['files']} files, "
                                                           f"{x['bytes']} bytes, verified") for x in d["pushed"]])
        return 0
    raise InputError(f"unknown archive action {args.action!r}")


def calibrate(args, out) -> int:
    from cell.cellcal.handeye import run_hand_eye
    from cell.cellcal.reverify import run_reverification

    if (args.backend or "") == "ur":
        _confirm(args, out, "This calibration moves the robot.")
    if args.what == "hand-eye":
        doc = run_hand_eye(args.cell_file, args.archive, out, backend=args.backend)
    else:
        doc = run_reverification(args.cell_file, args.archive, out, backend=args.backend)
    out.result(doc, lambda d: out.say(json.dumps({k: v for k, v in d.items() if not isinstance(v, (list, dict))},
                                                  default=str)))
    passed = doc.get("passed", True)
    return 0 if passed else 1
