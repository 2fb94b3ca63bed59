"""HIL session set-up: against URSim (``CELL_URSIM=1``) the simulated robot starts powered off, so the
session powers it on and releases the brakes through the dashboard server; a real robot is left as the
operator left it (powering a real arm on is an operator's act)."""
from __future__ import annotations

import os

import pytest


@pytest.fixture(scope="session", autouse=True)
def ursim_running():
    host = os.environ.get("CELL_UR_HOST")
    if host and os.environ.get("CELL_URSIM") == "1":
        from drivers.ur_dashboard import Dashboard

        with Dashboard(host) as dash:
            mode = dash.power_on_and_release(timeout_s=120.0)
            assert mode == "RUNNING", f"URSim robot mode {mode}"
    yield
