"""The UR dashboard server (port 29999): power on and release the brakes before a session, read the
robot mode, safety status and remote-control state. A line-based text protocol (UR's "Dashboard
server e-Series" manual): one command per line, one reply line each; the server greets with
``Connected: Universal Robots Dashboard Server``.

Used by the bring-up checks and the HIL tests (URSim starts powered off); the job itself never powers
a robot on: that is an operator's act.
"""
from __future__ import annotations

import socket
import time

from calibration.errors import NotConnectedError

PORT = 29999


class Dashboard:
    def __init__(self, host: str, port: int = PORT, timeout_s: float = 3.0):
        self.host, self.port, self.timeout_s = host, int(port), float(timeout_s)
        self._sock: socket.socket | None = None
        self._buf = b""

    def __enter__(self) -> Dashboard:
        try:
            self._sock = socket.create_connection((self.host, self.port), timeout=self.timeout_s)
            greeting = self._line()
        except OSError as exc:
            self.close()
            raise NotConnectedError(f"UR dashboard at {self.host}:{self.port}: cannot connect ({exc}); is the "
                                    "controller (or URSim) up and the address right?") from None
        if "Dashboard Server" not in greeting:
            self.close()
            raise NotConnectedError(f"UR dashboard at {self.host}:{self.port}: unexpected greeting {greeting!r}")
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        s, self._sock = self._sock, None
        if s is not None:
            s.close()

    def _line(self) -> str:
        while b"\n" not in self._buf:
            chunk = self._sock.recv(4096)
            if not chunk:
                raise OSError("the dashboard server closed the connection")
            self._buf += chunk
        line, self._buf = self._buf.split(b"\n", 1)
        return line.decode("utf-8", "replace").strip()

    def command(self, cmd: str) -> str:
        if self._sock is None:
            raise NotConnectedError(f"UR dashboard at {self.host}:{self.port}: not connected")
        try:
            self._sock.sendall(cmd.encode("ascii") + b"\n")
            return self._line()
        except OSError as exc:
            self.close()
            raise NotConnectedError(f"UR dashboard at {self.host}:{self.port}: '{cmd}' failed ({exc})") from None

    def robot_mode(self) -> str:
        return self.command("robotmode").split(":", 1)[-1].strip()

    def power_on_and_release(self, timeout_s: float = 60.0) -> str:
        """``power on``, wait for IDLE, ``brake release``, wait for RUNNING; the final robot mode."""
        deadline = time.monotonic() + timeout_s
        for cmd, want in (("power on", ("IDLE", "RUNNING")), ("brake release", ("RUNNING",))):
            if self.robot_mode() in want:
                continue
            self.command(cmd)
            while (mode := self.robot_mode()) not in want:
                if time.monotonic() > deadline:
                    raise NotConnectedError(f"UR at {self.host}: robot mode {mode} after '{cmd}' (wanted "
                                            f"{' or '.join(want)}) within {timeout_s:.0f} s; look at the pendant")
                time.sleep(0.5)
        return self.robot_mode()
