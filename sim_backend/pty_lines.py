"""The serving loop of an emulated serial device on a pseudo-terminal (the Gardasoft light controller, the Fluke
thermometer readout): read what the client wrote, cut it into command lines, write each line's reply back."""
from __future__ import annotations

import os
import select
import threading
from collections.abc import Callable


def serve_lines(master: int, stop: threading.Event, split: Callable[[bytes], tuple[list, bytes]],
                answer: Callable[[object], str | None]) -> None:
    """Until ``stop`` is set or the terminal goes away: read ``master``, ``split(buffer)`` into ``(lines, rest)``,
    write ``answer(line)`` back for each line that has one (latin-1; a reply that cannot be written ends the loop)."""
    buffer = b""
    while not stop.is_set():
        try:
            ready, _, _ = select.select([master], [], [], 0.02)
            if not ready:
                continue
            chunk = os.read(master, 1024)
        except (OSError, ValueError):
            return
        if not chunk:
            return
        lines, buffer = split(buffer + chunk)
        for line in lines:
            reply = answer(line)
            if reply is not None:
                try:
                    os.write(master, reply.encode("latin-1", "replace"))
                except OSError:
                    return
