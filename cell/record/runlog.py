"""The run log: everything a job does, as it happens, in an MCAP file.

Written without chunking and flushed after every message, so a file cut off by a
crash (SIGKILL, power) still yields every record up to the crash with
:func:`read_messages` (shared notes: a 1 MiB-chunked file cut after 1,000
messages keeps none of them; an unchunked one keeps all). Messages are JSON with
JSON Schemas (images use the Foxglove ``CompressedImage`` schema), so a standard
MCAP viewer shows them. A resumed job writes a new file, ``run.N.mcap``.
"""
from __future__ import annotations

import base64
import json
import os
import time
from pathlib import Path
from typing import Iterator

from mcap.reader import NonSeekingReader
from mcap.writer import CompressionType, Writer

import cell
from cell.record.jobfolder import to_jsonable

_SCHEMAS: dict[str, dict] = {
    "cell.State": {
        "type": "object",
        "properties": {"from": {"type": "string"}, "to": {"type": "string"}, "cause": {"type": "string"}},
    },
    "cell.JointState": {
        "type": "object",
        "properties": {
            "joints_rad": {"type": "array", "items": {"type": "number"}},
            "timestamp_s": {"type": "number"},
            "station": {"type": "string"},
        },
    },
    "foxglove.PoseInFrame": {
        "type": "object",
        "properties": {
            "timestamp": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
            "frame_id": {"type": "string"},
            "pose": {
                "type": "object",
                "properties": {
                    "position": {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}},
                    "orientation": {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}},
                },
            },
        },
    },
    "foxglove.CompressedImage": {
        "type": "object",
        "properties": {
            "timestamp": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
            "frame_id": {"type": "string"},
            "data": {"type": "string", "contentEncoding": "base64"},
            "format": {"type": "string"},
        },
    },
    "cell.Detections": {
        "type": "object",
        "properties": {
            "station": {"type": "string"},
            "ids": {"type": "array", "items": {"type": "string"}},
            "uv": {"type": "array", "items": {"type": "array", "items": {"type": "number"}}},
        },
    },
    "cell.Job": {
        "type": "object",
        "properties": {
            "job_id": {"type": "string"},
            "part": {"type": "object", "properties": {k: {"type": ["string", "null"]} for k in ("number", "revision", "serial")}},
            "operator": {"type": ["string", "null"]},
            "cell_id": {"type": ["string", "null"]},
        },
    },
    "cell.Exposure": {
        "type": "object",
        "description": "one triggered exposure at a station: trigger, frame, the robot state at the frame's instant",
        "properties": {
            "station": {"type": "string"},
            "attempt": {"type": "integer"},
            "outcome": {"type": "string", "enum": ["ok", "late", "duplicate", "missing", "stale", "moved"]},
            "detail": {"type": "string"},
            "trigger_host_s": {"type": "number"},
            "light": {"type": "string"},
            "frame_host_s": {"type": ["number", "null"]},
            "frame_id": {"type": ["integer", "null"]},
            "device_timestamp_ns": {"type": ["integer", "null"]},
            "latency_s": {"type": ["number", "null"]},
            "exposure_s": {"type": ["number", "null"]},
            "robot_timestamp_s": {"type": ["number", "null"]},
            "joints_rad": {"type": ["array", "null"], "items": {"type": "number"}},
            "settled_for_s": {"type": ["number", "null"]},
            "max_joint_speed_rad_s": {"type": ["number", "null"]},
        },
    },
    "foxglove.Log": {
        "type": "object",
        "properties": {
            "timestamp": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
            "level": {"type": "integer"},
            "message": {"type": "string"},
            "name": {"type": "string"},
        },
    },
}

TOPICS = {
    "/state": "cell.State",
    "/robot/joint_states": "cell.JointState",
    "/robot/flange_pose": "foxglove.PoseInFrame",
    "/camera/image": "foxglove.CompressedImage",
    "/detections": "cell.Detections",
    "/camera/exposure": "cell.Exposure",
    "/log": "foxglove.Log",
    "/job": "cell.Job",
}
LOG_LEVELS = {"debug": 1, "info": 2, "warning": 3, "error": 4, "fatal": 5}


def _stamp(t_ns: int) -> dict:
    return {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000}


class RunLog:
    """An append-only MCAP log of one session of a job."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self._f = open(self.path, "wb")
        self._w = Writer(self._f, use_chunking=False, compression=CompressionType.NONE)
        self._w.start(profile="", library=f"inspection-cell/{cell.__version__}")
        self._channels: dict[str, int] = {}
        schema_ids = {
            name: self._w.register_schema(name=name, encoding="jsonschema", data=json.dumps(s).encode())
            for name, s in _SCHEMAS.items()
        }
        for topic, schema in TOPICS.items():
            self._channels[topic] = self._w.register_channel(topic=topic, message_encoding="json", schema_id=schema_ids[schema])
        self._seq = 0
        self._f.flush()
        self.closed = False

    def write(self, topic: str, msg: dict, *, sync: bool = False) -> None:
        if self.closed:
            return
        t = time.time_ns()
        self._seq += 1
        self._w.add_message(self._channels[topic], log_time=t, publish_time=t, sequence=self._seq,
                            data=json.dumps(to_jsonable(msg)).encode())
        self._f.flush()
        if sync:
            os.fsync(self._f.fileno())

    # --- typed helpers -----------------------------------------------------
    def state(self, a: str, b: str, cause: str = "") -> None:
        self.write("/state", {"from": a, "to": b, "cause": cause}, sync=True)

    def job(self, job_id: str, meta: dict) -> None:
        """Which part (number, revision, serial), who runs it, on which cell: once per session."""
        self.write("/job", {"job_id": job_id, **meta}, sync=True)

    def log(self, level: str, message: str) -> None:
        self.write("/log", {"timestamp": _stamp(time.time_ns()), "level": LOG_LEVELS[level], "message": message,
                            "name": "cell"})

    def robot(self, joints, base_from_flange, timestamp_s: float, station: str = "") -> None:
        from scipy.spatial.transform import Rotation

        self.write("/robot/joint_states", {"joints_rad": joints, "timestamp_s": timestamp_s, "station": station})
        q = Rotation.from_matrix(base_from_flange[:3, :3]).as_quat()
        p = base_from_flange[:3, 3]
        self.write("/robot/flange_pose", {
            "timestamp": _stamp(int(timestamp_s * 1e9)), "frame_id": "base",
            "pose": {"position": dict(zip("xyz", map(float, p))), "orientation": dict(zip("xyzw", map(float, q)))},
        })

    def image(self, png: bytes, station: str) -> None:
        self.write("/camera/image", {"timestamp": _stamp(time.time_ns()), "frame_id": f"camera/{station}",
                                     "data": base64.b64encode(png).decode(), "format": "png"})

    def exposure(self, record: dict) -> None:
        """One triggered exposure (:class:`cell.stages.exposure.Exposure` as a dict), good or faulted."""
        self.write("/camera/exposure", record, sync=record.get("outcome") != "ok")

    def detections(self, station: str, ids: list[str], uv) -> None:
        self.write("/detections", {"station": station, "ids": ids, "uv": uv})

    def close(self) -> None:
        """Finish and close the file; the file is closed even when finishing fails (a full disk): then raises."""
        if not self.closed:
            self.closed = True
            try:
                self._w.finish()
                self._f.flush()
                os.fsync(self._f.fileno())
            finally:
                self._f.close()


def read_messages(path: Path) -> Iterator[tuple[str, dict]]:
    """Every complete message of a run log, even one cut off by a crash: ``(topic, message)``."""
    with open(path, "rb") as f:
        reader = NonSeekingReader(f, validate_crcs=False)
        it = reader.iter_messages(log_time_order=False)  # in file order: a torn tail does not hide the rest
        while True:
            try:
                _schema, channel, message = next(it)
            except StopIteration:
                return
            except Exception:  # a torn last record (struct.error, McapError, EndOfFile...)
                return
            yield channel.topic, json.loads(message.data)


def next_log_path(folder: Path) -> Path:
    if not (folder / "run.mcap").exists():
        return folder / "run.mcap"
    k = 1
    while (folder / f"run.{k}.mcap").exists():
        k += 1
    return folder / f"run.{k}.mcap"
