"""What a job's journal vouches for, and whether the folder still holds it.

Every file a job stores is journalled with its sha256 when it is written: images in their
``station_done`` record, every other result in the ``stage_done`` record of the stage that
wrote it (``files``: path -> sha256; the latest record of a path wins). From the journal alone
this module says which stages are finished, which stations acquired, and what each stored file
must hash to; :func:`check_stored` then compares the folder with it, so that ``cell resume``
verifies before it acts and the manifest vouches only for files that verify.

Every result written while a stage runs is also journalled as it is written (``stored``: path,
sha256, stage; before its rename, so a kill between the two leaves the previous version, which
is then accepted too).

Records that change what counts: ``reopened`` {stage} (that stage and every later one are to
be done again), ``station_invalid`` {station} (its image failed verification: the station is
acquired again), ``quarantined`` {file} (a file that failed verification, moved to
``damaged/``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

from cell.record.jobfolder import JobFolder, sha256_file
from cell.states import STAGES

_ORDER = {s.value: i for i, s in enumerate(STAGES)}


def finished_stages(recs: list[dict]) -> set[str]:
    """Stages whose result stands: a ``stage_done`` not voided by a later ``reopened`` of it or an earlier stage."""
    done: set[str] = set()
    for r in recs:
        if r.get("event") == "stage_done":
            done.add(r.get("stage"))
        elif r.get("event") == "reopened" and r.get("stage") in _ORDER:
            k = _ORDER[r["stage"]]
            done = {s for s in done if _ORDER.get(s, -1) < k}
    return done


def acquired(recs: list[dict]) -> dict[str, dict]:
    """Station id -> its standing ``station_done`` record (one not voided by a later ``station_invalid``)."""
    out: dict[str, dict] = {}
    for r in recs:
        if r.get("event") == "station_done" and "station" in r:
            out[r["station"]] = r
        elif r.get("event") == "station_invalid":
            out.pop(r.get("station"), None)
    return out


def recorded_files(recs: list[dict]) -> dict[str, tuple[str, str]]:
    """Path -> (sha256, stage that wrote it) of every non-image file the journal vouches for (latest version)."""
    return {rel: versions[-1] for rel, versions in _versions(recs).items()}


def _versions(recs: list[dict]) -> dict[str, list[tuple[str, str]]]:
    """Path -> the (sha256, stage) the journal recorded for it, oldest first ('quarantined' starts afresh)."""
    out: dict[str, list[tuple[str, str]]] = {}
    for r in recs:
        ev = r.get("event")
        if ev == "stored" and r.get("file"):
            out.setdefault(r["file"], []).append((r.get("sha256", ""), r.get("stage", "")))
        elif ev == "stage_done" and isinstance(r.get("files"), dict):
            for rel, sha in r["files"].items():
                out.setdefault(rel, []).append((sha, r.get("stage", "")))
        elif ev == "quarantined":
            out.pop(r.get("file"), None)
    return out


def _acceptable(recs: list[dict]) -> dict[str, tuple[set[str], str]]:
    """Path -> (sha256 values the file may have, stage): the latest version; and, when that version is a
    ``stored`` record of the last session (journalled before its rename, which a kill may have
    prevented), the one before it too."""
    out = {}
    last_session_from = max((i for i, r in enumerate(recs) if r.get("event") in ("created", "resumed")), default=0)
    stored_late = {r.get("file"): r.get("sha256") for r in recs[last_session_from:] if r.get("event") == "stored"}
    for rel, versions in _versions(recs).items():
        ok = {versions[-1][0]}
        if len(versions) > 1 and stored_late.get(rel) == versions[-1][0]:
            ok.add(versions[-2][0])
        out[rel] = (ok, versions[-1][1])
    return out


def expected_hashes(recs: list[dict]) -> dict[str, str]:
    """Path -> sha256 the journal vouches for: images of the acquired stations and every stage's files."""
    out = {rel: sha for rel, (sha, _) in recorded_files(recs).items()}
    for r in acquired(recs).values():
        if r.get("image") and r.get("sha256"):
            out[r["image"]] = r["sha256"]
    return out


def changed_files(folder: JobFolder, recs: list[dict]) -> dict[str, str]:
    """Files (not images) that are new or differ from what the journal holds: path -> sha256, to journal."""
    known = recorded_files(recs)
    out = {}
    for rel in folder.stored_files():
        if rel.startswith("images/"):
            continue
        sha = sha256_file(folder.path / rel)
        if known.get(rel, ("",))[0] != sha:
            out[rel] = sha
    return out


@dataclass
class Findings:
    """What failed verification: stations to acquire again, and other files with the stage that wrote them."""

    stations: dict[str, str] = field(default_factory=dict)  # station id -> why
    files: dict[str, tuple[str, str]] = field(default_factory=dict)  # path -> (why, stage)

    def __bool__(self) -> bool:
        return bool(self.stations or self.files)


def _image_readable(path) -> bool:
    import cv2

    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED) is not None


def check_stored(folder: JobFolder, recs: list[dict], *, decode_images: bool = True) -> Findings:
    """Compare the folder with the journal: each image (sha256, and that it decodes), each other file."""
    found = Findings()
    for sid, r in acquired(recs).items():
        p = folder.path / r.get("image", "")
        if not r.get("image") or not p.is_file():
            found.stations[sid] = f"its image {r.get('image')} is missing"
        elif sha256_file(p) != r.get("sha256"):
            found.stations[sid] = f"its image {r['image']} changed since it was stored (sha256 differs from the journal)"
        elif decode_images and not _image_readable(p):
            found.stations[sid] = f"its image {r['image']} cannot be decoded"
    for rel, (ok, stage) in _acceptable(recs).items():
        p = folder.path / rel
        if not p.is_file():
            found.files[rel] = ("missing", stage)
        elif sha256_file(p) not in ok:
            found.files[rel] = ("changed since it was stored (sha256 differs from the journal)", stage)
    return found


def journal_against_manifest(folder: JobFolder) -> str | None:
    """What is wrong with the journal against the manifest that last closed the job (None: nothing, or no manifest).

    A closed job's manifest holds its journal's sha256 and length. A journal shorter than that, or whose first
    bytes are not those, lost or changed records after the job closed: cut at a line boundary it still reads whole,
    and a resume or a repair would take the job for one that never finished (an outside check: a resume drove a DONE
    job again and overwrote its images). A journal that only grew (records appended after the close) is whole."""
    import hashlib
    import json as _json

    from cell.record.jobfolder import MANIFEST

    p = folder.path / MANIFEST
    if not p.is_file():
        return None
    try:
        meta = _json.loads(p.read_text(encoding="utf-8"))["files"]["journal.jsonl"]
        want, n = str(meta["sha256"]), int(meta["bytes"])
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError):
        return None  # a damaged manifest is verify's to say; it vouches for nothing here
    data = (folder.path / "journal.jsonl").read_bytes() if (folder.path / "journal.jsonl").is_file() else b""
    if len(data) < n:
        return (f"{folder.path / 'journal.jsonl'}: {len(data)} bytes, shorter than the {n} the job's manifest recorded "
                "when it closed: records were lost after the close")
    if hashlib.sha256(data[:n]).hexdigest() != want:
        return (f"{folder.path / 'journal.jsonl'}: its first {n} bytes differ from the journal the job's manifest "
                "recorded when it closed: records were changed after the close")
    return None
