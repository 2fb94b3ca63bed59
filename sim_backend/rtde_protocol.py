"""The public RTDE wire protocol (Universal Robots, port 30004), server side, and the
contract with ur-rtde's control script.

Only what a controller needs to answer a client such as ur-rtde: framing, the
package types, the variable table (name -> RTDE type), recipes that pack outputs
and unpack inputs (everything big-endian, as the RTDE guide states; a package is
``uint16 size`` (header included), ``uint8 type``, payload), a small threaded TCP
service, and :func:`check_control_script`: the command ids and register layout of
the script ur-rtde uploads, which the loopback controller plays.
"""
from __future__ import annotations

import re
import select
import socket
import struct
import threading
import time
from dataclasses import dataclass

HEADER = struct.Struct(">HB")

REQUEST_PROTOCOL_VERSION = ord("V")
GET_URCONTROL_VERSION = ord("v")
TEXT_MESSAGE = ord("M")
DATA_PACKAGE = ord("U")
SETUP_OUTPUTS = ord("O")
SETUP_INPUTS = ord("I")
START = ord("S")
PAUSE = ord("P")

# RTDE type name -> struct format (without the byte-order mark)
TYPE_FORMATS: dict[str, str] = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}

_V6 = "VECTOR6D"

# Controller outputs (what a client may subscribe to) and their types, from the public RTDE guide.
OUTPUT_TYPES: dict[str, str] = {
    "timestamp": "DOUBLE",
    "target_q": _V6, "target_qd": _V6, "target_qdd": _V6, "target_current": _V6, "target_moment": _V6,
    "actual_q": _V6, "actual_qd": _V6, "actual_qdd": _V6, "actual_current": _V6, "actual_moment": _V6,
    "joint_control_output": _V6,
    "actual_TCP_pose": _V6, "actual_TCP_speed": _V6, "actual_TCP_force": _V6,
    "target_TCP_pose": _V6, "target_TCP_speed": _V6,
    "actual_digital_input_bits": "UINT64", "actual_digital_output_bits": "UINT64",
    "joint_temperatures": _V6, "actual_execution_time": "DOUBLE",
    "robot_mode": "INT32", "joint_mode": "VECTOR6INT32", "safety_mode": "INT32", "safety_status": "INT32",
    "actual_tool_accelerometer": "VECTOR3D", "speed_scaling": "DOUBLE", "target_speed_fraction": "DOUBLE",
    "actual_momentum": "DOUBLE", "actual_main_voltage": "DOUBLE", "actual_robot_voltage": "DOUBLE",
    "actual_robot_current": "DOUBLE", "actual_joint_voltage": _V6,
    "runtime_state": "UINT32", "robot_status_bits": "UINT32", "safety_status_bits": "UINT32",
    "standard_analog_input0": "DOUBLE", "standard_analog_input1": "DOUBLE",
    "standard_analog_output0": "DOUBLE", "standard_analog_output1": "DOUBLE",
    "ft_raw_wrench": _V6, "payload": "DOUBLE", "payload_cog": "VECTOR3D", "payload_inertia": _V6,
    "elbow_position": "VECTOR3D", "elbow_velocity": "VECTOR3D",
    "output_bit_registers0_to_31": "UINT32", "output_bit_registers32_to_63": "UINT32",
    **{f"output_int_register_{i}": "INT32" for i in range(48)},
    **{f"output_double_register_{i}": "DOUBLE" for i in range(48)},
}

# Controller inputs (what a client may write).
INPUT_TYPES: dict[str, str] = {
    **{f"input_int_register_{i}": "INT32" for i in range(48)},
    **{f"input_double_register_{i}": "DOUBLE" for i in range(48)},
    "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
    "external_force_torque": _V6,
    "speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE",
    "standard_digital_output_mask": "UINT8", "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8", "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8", "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8", "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
}


class ProtocolError(Exception):
    """A client sent something that is not RTDE."""


def split_names(payload: bytes) -> list[str]:
    """Comma-separated variable names; ur-rtde ends its lists with a comma (an empty name): dropped."""
    return [n.strip() for n in payload.decode("ascii", "replace").split(",") if n.strip()]


def pack(kind: int, payload: bytes = b"") -> bytes:
    """One package: header + payload."""
    return HEADER.pack(HEADER.size + len(payload), kind) + payload


def recv_exact(sock: socket.socket, n: int) -> bytes:
    """Read exactly ``n`` bytes; raises ``ConnectionError`` on EOF."""
    chunks = bytearray()
    while len(chunks) < n:
        chunk = sock.recv(n - len(chunks))
        if not chunk:
            raise ConnectionError("peer closed the connection")
        chunks.extend(chunk)
    return bytes(chunks)


def read_package(sock: socket.socket) -> tuple[int, bytes]:
    """Read one package from ``sock``: (type, payload)."""
    size, kind = HEADER.unpack(recv_exact(sock, HEADER.size))
    if size < HEADER.size:
        raise ProtocolError(f"package size {size} smaller than its header")
    return kind, recv_exact(sock, size - HEADER.size)


@dataclass(frozen=True)
class Recipe:
    """A list of variables and how they are packed on the wire.

    ``types`` holds the RTDE type of each name, or ``NOT_FOUND`` for a name the
    controller lacks (then the recipe is not usable: ``valid`` is False).
    """

    recipe_id: int
    names: tuple[str, ...]
    types: tuple[str, ...]

    @classmethod
    def make(cls, recipe_id: int, names: list[str], table: dict[str, str]) -> Recipe:
        return cls(recipe_id, tuple(names), tuple(table.get(n, "NOT_FOUND") for n in names))

    @property
    def valid(self) -> bool:
        return all(t in TYPE_FORMATS for t in self.types)

    @property
    def struct(self) -> struct.Struct:
        return struct.Struct(">B" + "".join(TYPE_FORMATS[t] for t in self.types))

    def setup_reply(self) -> bytes:
        return bytes([self.recipe_id if self.valid else 0]) + ",".join(self.types).encode()

    def pack_values(self, values: dict) -> bytes:
        """A data package of this (output) recipe from ``values`` (name -> scalar or sequence)."""
        flat: list = [self.recipe_id]
        for name, kind in zip(self.names, self.types):
            v = values[name]
            if kind.startswith("VECTOR"):
                flat.extend(float(x) if kind.endswith("D") else int(x) for x in v)
            elif kind == "DOUBLE":
                flat.append(float(v))
            elif kind == "BOOL":
                flat.append(bool(v))
            else:
                flat.append(int(v))
        return pack(DATA_PACKAGE, self.struct.pack(*flat))

    def unpack_values(self, payload: bytes) -> dict:
        """Name -> value of an (input) data package payload (recipe id byte included)."""
        fields = self.struct.unpack(payload)
        out, k = {}, 1
        for name, kind in zip(self.names, self.types):
            fmt = TYPE_FORMATS[kind]
            count = int(fmt[0]) if fmt[0].isdigit() else 1
            out[name] = fields[k] if count == 1 else tuple(fields[k:k + count])
            k += count
        return out


class TcpService:
    """A small TCP server on one loopback address and port, one thread per client.

    ``handler(conn, service)`` serves one client until it returns or the socket
    fails. ``drop_clients`` closes every client socket (a pulled cable);
    ``refuse_until`` makes new clients be closed at once until that wall time.
    ``close`` stops the listener and every client thread.
    """

    def __init__(self, host: str, port: int, handler, name: str):
        self.host, self.port, self.name = host, port, name
        self._handler = handler
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._clients: dict[socket.socket, threading.Thread] = {}
        self.refuse_until = 0.0
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._listener.bind((host, port))
        except OSError as exc:
            self._listener.close()
            raise OSError(f"loopback UR controller: cannot bind {host}:{port} ({exc}); "
                          "is another controller using this address?") from exc
        self._listener.listen(8)
        self._thread = threading.Thread(target=self._accept_loop, name=f"{name}-accept", daemon=True)
        self._thread.start()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self._listener], [], [], 0.05)
            if not ready:
                continue
            try:
                conn, _ = self._listener.accept()
            except OSError:
                continue
            if time.monotonic() < self.refuse_until:
                conn.close()
                continue
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.settimeout(1.0)
            thread = threading.Thread(target=self._serve, args=(conn,), name=f"{self.name}-client", daemon=True)
            with self._lock:
                self._clients[conn] = thread
            thread.start()

    def _serve(self, conn: socket.socket) -> None:
        try:
            self._handler(conn, self)
        except (OSError, ConnectionError, ProtocolError, struct.error):
            pass
        finally:
            with self._lock:
                self._clients.pop(conn, None)
            _close_quietly(conn)

    def wait_readable(self, conn: socket.socket) -> bool:
        """Block until ``conn`` has data (True) or the service stops (False)."""
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([conn], [], [], 0.05)
            except (OSError, ValueError):
                raise ConnectionError("socket closed") from None
            if ready:
                return True
        return False

    def drop_clients(self) -> None:
        with self._lock:
            conns = list(self._clients)
        for conn in conns:
            _close_quietly(conn)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._listener.close()
        self.drop_clients()
        with self._lock:
            threads = list(self._clients.values())
        for thread in threads:
            thread.join(timeout=2.0)


def _close_quietly(conn: socket.socket) -> None:
    try:
        conn.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    conn.close()


# ur-rtde's command ids that this controller plays, and what each block of the
# uploaded script must contain for the ids and register layout to mean what we play.
PLAYED_COMMANDS: dict[int, tuple[str, tuple[str, ...]]] = {
    1: ("movej", ("q = q_from_input_float_registers(0)", "velocity = read_input_float_reg(6)",
                  "acceleration = read_input_float_reg(7)", "async = read_input_integer_reg(1)",
                  "movej(q, a=acceleration, v=velocity)")),
    3: ("movel", ("pose = pose_from_input_float_registers(0)", "velocity = read_input_float_reg(6)",
                  "acceleration = read_input_float_reg(7)", "async = read_input_integer_reg(1)",
                  "movel(pose, a=acceleration, v=velocity)")),
    29: ("set_tcp", ("pose = pose_from_input_float_registers(0)", "set_tcp(pose)")),
    31: ("protective_stop", ("protective_stop()",)),
    33: ("stopl", ("exec_stopl_stopj(cmd",)),
    34: ("stopj", ("exec_stopl_stopj(cmd",)),
    35: ("set_watchdog", ("watchdog_min_frequency = read_input_float_reg(0)",
                          'rtde_set_watchdog("input_int_register_0", watchdog_min_frequency, "stop")')),
    36: ("is_pose_within_safety_limits", ("pose = pose_from_input_float_registers(0)",
                                          "safe_pose = is_within_safety_limits(pose)", "write_output_integer_reg(1, 1)",
                                          "write_output_integer_reg(1, 0)")),
    37: ("is_joints_within_safety_limits", ("q = q_from_input_float_registers(0)", "safe_q = is_within_safety_limits(q)",
                                            "write_output_integer_reg(1, 1)", "write_output_integer_reg(1, 0)")),
    255: ("stop_script", ("Received stop script",)),
}
# Fragments outside the command blocks that the handshake relies on.
SCRIPT_FRAGMENTS: tuple[str, ...] = (
    "def signal_ready():\n        write_output_integer_reg(0, 1)",
    "def signal_done_with_cmd():\n        write_output_integer_reg(0, 2)",
    "cmd = read_input_integer_reg(0)",
    "write_output_integer_reg(2, reg_value)",
    "deceleration_rate = read_input_float_reg(0)\n      async = read_input_integer_reg(1)",
    "if cmd != 255:\n              signal_done_with_cmd()",
)


class ScriptContractError(ValueError):
    """The uploaded control script does not match the commands this controller plays."""


def command_blocks(script: str) -> dict[int, str]:
    """Command id -> text of its ``if/elif cmd == N:`` block in ``process_cmd``."""
    start = script.find("def process_cmd(cmd):")
    if start < 0:
        raise ScriptContractError("no 'def process_cmd(cmd):' in the uploaded script")
    body = script[start:]
    marks = list(re.finditer(r"^\s*(?:if|elif) cmd == (\d+):", body, flags=re.M))
    blocks = {}
    for k, m in enumerate(marks):
        end = marks[k + 1].start() if k + 1 < len(marks) else len(body)
        blocks.setdefault(int(m.group(1)), body[m.end():end])
    return blocks


def check_control_script(script: str) -> int:
    """Check ur-rtde's control script against :data:`PLAYED_COMMANDS`; return the register offset.

    Raises ``ScriptContractError`` naming the first mismatch (an ur-rtde upgrade
    that renumbered a command or moved an argument to another register).
    """
    blocks = command_blocks(script)
    for cmd, (name, needles) in PLAYED_COMMANDS.items():
        block = blocks.get(cmd)
        if block is None:
            raise ScriptContractError(f"command {cmd} ({name}) is missing from the uploaded script")
        for needle in needles:
            if needle not in block:
                raise ScriptContractError(f"command {cmd} ({name}): expected '{needle}' in its block")
    for needle in SCRIPT_FRAGMENTS:
        if needle not in script:
            raise ScriptContractError(f"expected '{needle}' in the uploaded script")
    m = re.search(r"global reg_offset_int = (?:#[^\n]*\n)?\s*(\d+)", script)
    if m is None:
        raise ScriptContractError("no integer register offset injected into the script")
    return int(m.group(1))
