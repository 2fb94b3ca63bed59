"""Shared fixtures: a guard that fails a test leaving threads or child processes behind."""
from __future__ import annotations

import os
import threading
import time

import pytest


def _children() -> set[int]:
    try:
        with open(f"/proc/{os.getpid()}/task/{os.getpid()}/children") as f:
            return {int(p) for p in f.read().split()}
    except OSError:
        return set()


@pytest.fixture(autouse=True)
def no_leaked_threads_or_processes(request):
    """Fail a test that leaves threads or child processes running."""
    before_threads = {t.ident for t in threading.enumerate()}
    before_children = _children()
    yield
    deadline = time.monotonic() + 3.0
    while True:
        extra = [t for t in threading.enumerate() if t.ident not in before_threads and t.is_alive() and not t.daemon]
        extra_daemon = [t for t in threading.enumerate() if t.ident not in before_threads and t.is_alive() and t.daemon]
        kids = _children() - before_children
        if not extra and not extra_daemon and not kids:
            return
        if time.monotonic() > deadline:
            break
        time.sleep(0.05)
    names = [t.name for t in extra + extra_daemon]
    # thread pools owned by libraries (e.g. concurrent.futures in numpy/BLAS) are named; report only ours
    ours = [n for n in names if not n.startswith(("ThreadPoolExecutor", "QueueFeederThread", "asyncio"))]
    if ours or kids:
        pytest.fail(f"test left behind threads {ours} and child processes {sorted(kids)}")
