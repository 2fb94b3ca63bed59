"""Write URDF models of Universal Robots arms from their published DH parameters.

The kinematic chain follows the standard Denavit-Hartenberg convention that Universal
Robots publish: ``A_i = Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``. Joint ``i`` of the URDF sits
at the origin of DH frame ``i-1`` with its axis along that frame's z, and the fixed
transform ``Tz(d_i) Tx(a_i) Rx(alpha_i)`` is the origin of the next joint. The last fixed
joint ends at ``tool0``, the flange frame, which is the controller's TCP with zero TCP
offset; the root link ``base`` is the controller's base frame (ur_description's ``base``,
which is ``base_link`` turned by pi about z). So the FK of this URDF equals what the robot
reports as ``getActualTCPPose`` with no TCP set.

Collision shapes are cylinders (one or two per link) laid along the physical links, with
the lateral offsets of the real arm (shoulder, elbow) that the DH model folds into ``d4``.

Run ``python -m planning.robots.make_urdf`` to rewrite ``ur5e.urdf`` and ``ur10e.urdf``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["URParams", "UR_PARAMS", "urdf_text", "write_urdfs", "JOINT_NAMES", "LINK_NAMES"]

JOINT_NAMES = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)
LINK_NAMES = (
    "base",
    "shoulder_link",
    "upper_arm_link",
    "forearm_link",
    "wrist_1_link",
    "wrist_2_link",
    "wrist_3_link",
)


@dataclass(frozen=True)
class URParams:
    """Published parameters of one UR arm (metres, radians, seconds).

    Attributes:
        name: model name ("ur5e").
        d, a, alpha: (6,) DH parameters, standard convention.
        max_velocity_rad_s: (6,) joint speed limits.
        effort_nm: (6,) joint torque limits.
        reach_m: the manufacturer's stated reach (flange centre from the base axis).
        shoulder_offset_m: lateral offset of the upper arm from the base axis, along the
            shoulder axis (the DH model folds it, with the elbow and wrist offsets, into d4).
        elbow_offset_m: offset of the forearm back towards the base axis plane.
        radius_m: cylinder radii of (base, shoulder, upper arm, elbow, forearm, wrist, flange).
    """

    name: str
    d: tuple[float, ...]
    a: tuple[float, ...]
    alpha: tuple[float, ...]
    max_velocity_rad_s: tuple[float, ...]
    effort_nm: tuple[float, ...]
    reach_m: float
    shoulder_offset_m: float
    elbow_offset_m: float
    radius_m: tuple[float, ...]


_ALPHA = (np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0)

UR_PARAMS: dict[str, URParams] = {
    "ur5e": URParams(
        name="ur5e",
        d=(0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996),
        a=(0.0, -0.425, -0.3922, 0.0, 0.0, 0.0),
        alpha=_ALPHA,
        max_velocity_rad_s=(np.pi,) * 6,
        effort_nm=(150.0, 150.0, 150.0, 28.0, 28.0, 28.0),
        reach_m=0.85,
        shoulder_offset_m=0.138,
        elbow_offset_m=0.131,
        radius_m=(0.076, 0.075, 0.055, 0.060, 0.045, 0.045, 0.0315),
    ),
    "ur10e": URParams(
        name="ur10e",
        d=(0.1807, 0.0, 0.0, 0.17415, 0.11985, 0.11655),
        a=(0.0, -0.6127, -0.57155, 0.0, 0.0, 0.0),
        alpha=_ALPHA,
        max_velocity_rad_s=(2 * np.pi / 3, 2 * np.pi / 3, np.pi, np.pi, np.pi, np.pi),
        effort_nm=(330.0, 330.0, 150.0, 56.0, 56.0, 56.0),
        reach_m=1.30,
        shoulder_offset_m=0.176,
        elbow_offset_m=0.137,
        radius_m=(0.095, 0.095, 0.068, 0.075, 0.060, 0.060, 0.0315),
    ),
}


def _segments(p: URParams) -> dict[str, list[tuple[np.ndarray, np.ndarray, float]]]:
    """Collision cylinders per link as (start (3,), end (3,), radius) in the link frame."""
    d1, d4, d5, d6 = p.d[0], p.d[3], p.d[4], p.d[5]
    a2, a3 = p.a[1], p.a[2]
    so, eo = p.shoulder_offset_m, p.elbow_offset_m
    r_base, r_sh, r_up, r_el, r_fo, r_wr, r_fl = p.radius_m
    v = lambda *x: np.array(x, dtype=float)  # noqa: E731
    h_base = 0.55 * d1
    return {
        # fixed base drum on the table
        "base": [(v(0, 0, 0), v(0, 0, h_base), r_base)],
        # rotating shoulder drum, then the shoulder joint housing along the lift axis (-y here)
        "shoulder_link": [
            (v(0, 0, h_base), v(0, 0, d1), r_sh),
            (v(0, 0, d1), v(0, -so, d1), r_sh),
        ],
        # upper arm tube, offset by the shoulder offset along the joint axis (+z), and elbow housing
        "upper_arm_link": [
            (v(0, 0, so), v(a2, 0, so), r_up),
            (v(a2, 0, so + r_el * 0.5), v(a2, 0, so - eo), r_el),
        ],
        # forearm tube
        "forearm_link": [(v(0, 0, so - eo), v(a3, 0, so - eo), r_fo)],
        # wrist 1 housing along its own axis up to the wrist 2 axis (coaxial with the joint,
        # so it may ride on this link), then the wrist 2 housing along the wrist 2 axis (-y)
        "wrist_1_link": [
            (v(0, 0, so - eo), v(0, 0, d4), r_wr),
            (v(0, 0, d4), v(0, -d5 + r_wr, d4), r_wr),
        ],
        # wrist 3 housing along the wrist 3 axis (+y in this frame), short of the flange face
        "wrist_2_link": [(v(0, 0, d5), v(0, d6 - 0.015, d5), r_wr)],
        # flange disc
        "wrist_3_link": [(v(0, 0, d6 - 0.015), v(0, 0, d6 - 0.001), r_fl)],
    }


def _rpy_z_to(direction: np.ndarray) -> tuple[float, float, float]:
    """Roll-pitch-yaw (URDF, fixed axes x-y-z) of a rotation taking +z to ``direction``."""
    u = direction / np.linalg.norm(direction)
    pitch = float(np.arctan2(np.hypot(u[0], u[1]), u[2]))
    yaw = float(np.arctan2(u[1], u[0]))
    return 0.0, pitch, yaw  # Rz(yaw) Ry(pitch) e_z = u


def _f(x: float) -> str:
    return repr(float(x)) if x != 0 else "0"


def urdf_text(p: URParams) -> str:
    """The URDF of one arm (string)."""
    segs = _segments(p)
    lines = [
        '<?xml version="1.0"?>',
        f"<!-- generated by planning/robots/make_urdf.py from the published DH parameters of the {p.name.upper()} -->",
        f'<robot name="{p.name}">',
    ]
    for link in LINK_NAMES:
        lines.append(f'  <link name="{link}">')
        for start, end, radius in segs[link]:
            mid = 0.5 * (start + end)
            length = float(np.linalg.norm(end - start))
            r, pt, y = _rpy_z_to(end - start)
            lines += [
                "    <collision>",
                f'      <origin xyz="{_f(mid[0])} {_f(mid[1])} {_f(mid[2])}" rpy="{_f(r)} {_f(pt)} {_f(y)}"/>',
                f'      <geometry><cylinder radius="{_f(radius)}" length="{_f(length)}"/></geometry>',
                "    </collision>",
            ]
        lines.append("  </link>")
    lines.append('  <link name="tool0"/>')
    for i, joint in enumerate(JOINT_NAMES):
        if i == 0:  # joint 1 at the base origin
            a, d, alpha = 0.0, 0.0, 0.0
        else:
            a, d, alpha = p.a[i - 1], p.d[i - 1], p.alpha[i - 1]
        lim = 2 * np.pi  # the hardware range; cells usually narrow the elbow (load_robot)
        lines += [
            f'  <joint name="{joint}" type="revolute">',
            f'    <parent link="{LINK_NAMES[i]}"/>',
            f'    <child link="{LINK_NAMES[i + 1]}"/>',
            f'    <origin xyz="{_f(a)} 0 {_f(d)}" rpy="{_f(alpha)} 0 0"/>',
            '    <axis xyz="0 0 1"/>',
            f'    <limit lower="{_f(-lim)}" upper="{_f(lim)}" effort="{_f(p.effort_nm[i])}" '
            f'velocity="{_f(p.max_velocity_rad_s[i])}"/>',
            "  </joint>",
        ]
    lines += [
        '  <joint name="wrist_3_link-tool0_fixed_joint" type="fixed">',
        '    <parent link="wrist_3_link"/>',
        '    <child link="tool0"/>',
        f'    <origin xyz="{_f(p.a[5])} 0 {_f(p.d[5])}" rpy="{_f(p.alpha[5])} 0 0"/>',
        "  </joint>",
        "</robot>",
        "",
    ]
    return "\n".join(lines)


def write_urdfs(folder: Path | None = None) -> list[Path]:
    """Write ``<name>.urdf`` for every arm in UR_PARAMS into ``folder`` (default: this package)."""
    folder = Path(folder) if folder is not None else Path(__file__).parent
    paths = []
    for name, params in UR_PARAMS.items():
        path = folder / f"{name}.urdf"
        path.write_text(urdf_text(params))
        paths.append(path)
    return paths


if __name__ == "__main__":  # pragma: no cover
    for written in write_urdfs():
        print(written)
