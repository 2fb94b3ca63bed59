"""URDF models of the cell's robots (UR5e, UR10e), generated from published DH parameters.

``urdf_path(name)`` gives the file; ``UR_PARAMS[name]`` the parameters it was written from.
"""
from __future__ import annotations

from pathlib import Path

from planning.robots.make_urdf import JOINT_NAMES, LINK_NAMES, UR_PARAMS, URParams, urdf_text

__all__ = ["JOINT_NAMES", "LINK_NAMES", "UR_PARAMS", "URParams", "urdf_text", "urdf_path"]


def urdf_path(name: str) -> Path:
    """Path of the packaged URDF of robot ``name`` ("ur5e" | "ur10e")."""
    return Path(__file__).parent / f"{name}.urdf"
