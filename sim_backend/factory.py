"""``make_sim_cell``: the one way to build a simulated cell (world, robot, camera, light).

The part's unknowns (its deviations from CAD, a fixture the CAD lacks, worn dots: ``damage``) go into the
:class:`World` built here and nowhere else: PLAN's twin (``cell.stages.preanalysis.twin_camera``) builds its own
world of the nominal part.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from calibration.camera import Intrinsics
from sim_backend.sim_camera import Photometry, RenderOptions, Sensor, SimCamera
from sim_backend.sim_robot import RobotLimits, SimRobot
from sim_backend.world import TargetDamage, World

__all__ = ["SimCell", "make_sim_cell"]


@dataclass
class SimCell:
    """The simulated devices, all coupled through one :class:`World`."""

    world: World
    robot: SimRobot
    camera: SimCamera
    light: Any = None  # a drivers.protocols.Light, or None

    def connect(self) -> None:
        for dev in (self.robot, self.camera, self.light):
            if dev is not None:
                dev.connect()

    def close(self) -> None:
        for dev in (self.light, self.camera, self.robot):
            if dev is not None:
                dev.close()


def make_sim_cell(
    part: Any,
    base_from_part: np.ndarray,
    flange_from_cam: np.ndarray,
    intr: Intrinsics,
    *,
    robot: str | Any = "ur5e",
    deviations: np.ndarray | None = None,
    image_sigma_px: float = 0.0,
    sensor: Sensor | None = None,
    photometry: Photometry | None = None,
    render: RenderOptions | None = None,
    seed: int = 0,
    motion: str = "instant",
    time_scale: float = 1.0,
    limits: RobotLimits | None = None,
    repeatability_rad: float = 0.0,
    initial_joints: np.ndarray | None = None,
    true_flange_from_cam: np.ndarray | None = None,
    true_base_from_part: np.ndarray | None = None,
    light: Any = None,
    fixture: Any = None,
    damage: TargetDamage | None = None,
    coded_family: str = "aruco",
    exposure_s: float = 0.002,
) -> SimCell:
    """Build a simulated cell around ``part``.

    Args:
        part: ``planning.part.Part`` (CAD nominal).
        base_from_part, flange_from_cam: (4, 4) the job's nominal values.
        intr: the camera's (true) intrinsics.
        robot: robot model name for ``planning.kinematics.load_robot``, or a loaded model.
        deviations: (n, 3) metres, true displacement of each target from CAD.
        image_sigma_px: per-target image jitter (the job's ``[sim] image_sigma_px``).
        sensor, photometry, render: camera simulation settings (defaults: 8-bit 5 MP style).
        seed: seed of every random stream in the cell.
        motion, time_scale, limits, repeatability_rad, initial_joints: see :class:`SimRobot`.
        true_flange_from_cam, true_base_from_part: the world's real values (default nominal).
        light: any ``drivers.protocols.Light`` (e.g. the serial driver on the pty emulator), or None.
        fixture: a trimesh in the part frame that hides dots but is not in the CAD (see :class:`World`).
        damage: worn coating of plain dots (:class:`~sim_backend.world.TargetDamage`); None: every dot intact.
        coded_family: how the coded targets look (``SimCamera``'s ``coded_family``).
        exposure_s: the camera's exposure time (the job's ``[camera] exposure_s``): the scene's brightness scales
            with it from the photometry's reference exposure (0.002 s), so a longer one clips more dots.
    """
    if isinstance(robot, str):
        from planning.kinematics import load_robot

        model = load_robot(robot)
    else:
        model = robot
    world = World(
        part,
        base_from_part,
        flange_from_cam,
        intr,
        deviations,
        true_base_from_part=true_base_from_part,
        true_flange_from_cam=true_flange_from_cam,
        seed=seed,
        fixture=fixture,
        damage=damage,
    )
    sim_robot = SimRobot(
        world,
        model,
        motion=motion,
        time_scale=time_scale,
        limits=limits or RobotLimits(),
        repeatability_rad=repeatability_rad,
        initial_joints=initial_joints,
    )
    opts = replace(render or RenderOptions(), image_sigma_px=float(image_sigma_px))
    camera = SimCamera(world, photometry=photometry or Photometry(), sensor=sensor or Sensor(), options=opts,
                       coded_family=coded_family, exposure_s=exposure_s)
    return SimCell(world=world, robot=sim_robot, camera=camera, light=light)
