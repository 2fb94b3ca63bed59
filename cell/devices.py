"""Open the cell's devices for a job: the simulated cell, or a real UR + camera + light.

The stages see only the Protocols of ``drivers.protocols``. With ``--backend ur``
in tests, the robot is the real ur-rtde client talking to the loopback UR
controller and the camera is the simulated one, following the pose the robot
reports (so a whole job runs through the real driver path).

The simulated cell carries the real part's unknowns: its deviations, a ``[sim] fixture`` and worn dots (``[sim]
damaged_targets``, :func:`_target_damage`); PLAN's twin (``cell.stages.preanalysis.twin_camera``) renders the
nominal part, without any of them.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field, replace

import numpy as np

from calibration.errors import InputError
from cell.jobspec import pose_matrix
from cell.loadedjob import LoadedJob
from drivers.protocols import Camera, Light, Robot, Thermometer


@dataclass
class Devices:
    robot: Robot
    camera: Camera
    light: Light | None = None
    world: object | None = None  # the simulated world, when there is one
    thermometer: Thermometer | None = None  # the part's thermometer readout, when the job reads it (decision 0053)
    _closers: list = field(default_factory=list)

    def close(self) -> None:
        for c in reversed(self._closers):
            try:
                c()
            except Exception:  # closing must never raise over the job's own outcome
                pass
        self._closers.clear()


def _true_poses(job: LoadedJob) -> tuple[np.ndarray, np.ndarray]:
    """The simulated cell's real part placement and hand-eye: nominal, times the [sim] errors."""
    s = job.spec
    k = s.scale
    true_bfp = s.base_from_part()
    true_ffc = s.flange_from_cam()
    if s.sim.base_from_part_true is not None:
        true_bfp = pose_matrix(s.sim.base_from_part_true, k)
    elif s.sim.base_from_part_error is not None:
        true_bfp = true_bfp @ pose_matrix(s.sim.base_from_part_error, k)
    if s.sim.flange_from_cam_error is not None:
        true_ffc = true_ffc @ pose_matrix(s.sim.flange_from_cam_error, k)
    return true_bfp, true_ffc


def _fixture_mesh(job: LoadedJob):
    """``[sim] fixture``: boxes in the part frame, one mesh in metres (None when there are none)."""
    if not job.spec.sim.fixture:
        return None
    import trimesh

    k = job.spec.scale
    boxes = [trimesh.creation.box(extents=[v * k for v in o.size], transform=pose_matrix(o.pose, k))
             for o in job.spec.sim.fixture]
    return trimesh.util.concatenate(boxes)


def _target_damage(job: LoadedJob):
    """``[sim] damaged_targets`` as the simulated world's :class:`~sim_backend.world.TargetDamage` (None: none)."""
    if not job.damaged_targets:
        return None
    from sim_backend.world import TargetDamage

    rows = job.damaged_targets
    return TargetDamage.of(len(job.part.targets.ids), [i for i, _ in rows], [d.kind for _, d in rows],
                           [d.lost for _, d in rows], [np.deg2rad(d.direction_deg) for _, d in rows],
                           [d.offset for _, d in rows])


def make_job_sim_cell(job: LoadedJob, seed_offset: int = 0, nominal_lens: bool = False):
    """The simulated cell of a job: the true part (CAD + deviations), its true placement and hand-eye, and its true
    lens (``[sim] lens``; decision 0054).

    ``seed_offset`` is added to ``[sim] seed``: sessions that must not share their noise (the positions
    of a reverification) pass different offsets. ``nominal_lens``: render the job's nominal lens instead (the
    detector's truth tools, whose truth is the nominal lens's projection, as the detector model was measured).
    """
    from cell.setup import robot_model
    from sim_backend.factory import make_sim_cell
    from sim_backend.sim_camera import Photometry, Sensor

    s = job.spec
    true_bfp, true_ffc = _true_poses(job)
    photometry = Photometry()
    if s.sim.dot_max_incidence_deg is not None:  # glare washes the dots out beyond this incidence
        photometry = replace(photometry, max_incidence_rad=float(np.deg2rad(s.sim.dot_max_incidence_deg)))
    return make_sim_cell(job.part, s.base_from_part(), s.flange_from_cam(),
                         s.intrinsics() if nominal_lens else s.true_intrinsics(), robot=robot_model(job),
                         deviations=job.deviations, image_sigma_px=s.sim.image_sigma_px, seed=s.sim.seed + seed_offset,
                         sensor=Sensor().with_noise_scale(s.sim.noise).with_camera(s.camera.pixel_format,
                                                                                    s.camera.gain_db)
                         .with_depth_of_field(s.camera.near * s.scale, s.camera.far * s.scale,
                                              s.sim.circle_of_confusion_px),
                         photometry=photometry,
                         fixture=_fixture_mesh(job), damage=_target_damage(job),
                         motion=s.sim.motion, time_scale=s.sim.time_scale, true_flange_from_cam=true_ffc,
                         true_base_from_part=true_bfp, coded_family=s.job.coded_family,
                         exposure_s=s.camera.exposure_s)


def open_devices(job: LoadedJob, backend: str, *, seed_offset: int = 0) -> Devices:
    s = job.spec
    if backend == "sim":
        sim = make_job_sim_cell(job, seed_offset)
        faults = _frame_faults_from_env()
        if faults:
            sim.camera.inject_frame_faults(faults, late_s=s.camera.frame_timeout_s + s.camera.exposure_s + 0.2)
        light, closers = sim.light, []
        if s.sim.light:
            # the real Gardasoft driver on the emulated controller (a pseudo-terminal): every pulse it fires is recorded
            from sim_backend.gardasoft_emulator import GardasoftSerialEmulator

            emulator = GardasoftSerialEmulator()
            closers.append(emulator.close)
            light = _gardasoft(emulator.port, s.cell)
            light.emulator = emulator
            if s.cell.light_input is not None:  # the camera's strobe line wired to the controller's trigger input
                sim.camera.strobe_out = lambda: emulator.controller.input_edge(s.cell.light_input)
        thermometer = None
        if s.thermal is not None and s.thermal.part_C == "probe":  # the real driver on the emulated readout (a pty)
            from cell.thermal import sim_part_C
            from drivers.thermometer import FlukeReadout
            from sim_backend.thermometer_emulator import ThermometerEmulator

            probe = ThermometerEmulator(temperature_C=sim_part_C(s), seed=s.sim.seed + seed_offset).start()
            closers.append(probe.stop)
            thermometer = FlukeReadout(probe.port)
        d = Devices(robot=sim.robot, camera=sim.camera, light=light, world=sim.world, thermometer=thermometer,
                    _closers=closers)
    elif backend == "ur":
        from cell.setup import robot_model
        from drivers.ur import CellLimits, URRobot

        k = s.scale
        reach = robot_model(job).params.reach_m
        box_lo = (np.asarray(s.cell.workspace_min) * k if s.cell.workspace_min is not None
                  else np.array([-reach, -reach, s.cell.table_z * k]))
        box_hi = (np.asarray(s.cell.workspace_max) * k if s.cell.workspace_max is not None
                  else np.array([reach, reach, reach + 0.2]))
        limits = CellLimits(max_joint_speed_rad_s=s.cell.max_joint_speed_rad_s,
                            max_joint_accel_rad_s2=s.cell.max_joint_accel_rad_s2,
                            max_tcp_speed_m_s=s.cell.max_tcp_speed_m_s, max_tcp_accel_m_s2=s.cell.max_tcp_accel_m_s2,
                            workspace_min_m=tuple(map(float, box_lo)), workspace_max_m=tuple(map(float, box_hi)))
        robot = URRobot(s.cell.host, limits=limits, robot=s.cell.robot)
        if s.camera.device is not None and s.camera.driver == "genicam":
            from drivers.genicam import GenICamCamera

            c = s.camera
            camera = GenICamCamera(c.device, producer=c.producer, pixel_format=c.pixel_format, exposure_s=c.exposure_s,
                                   gain_db=c.gain_db, trigger=c.trigger, strobe_line=c.strobe_line,
                                   timeout_s=c.frame_timeout_s, expected_size=(c.width, c.height))
            world = None
        elif s.camera.device is not None:
            from drivers.opencv_camera import OpenCVCamera

            camera = OpenCVCamera(int(s.camera.device) if s.camera.device.isdigit() else s.camera.device,
                                  exposure_s=s.camera.exposure_s)
            world = None
        else:
            # no real camera configured: the simulated camera follows the real robot's reported pose
            sim = make_job_sim_cell(job, seed_offset)
            world = sim.world
            camera = _FollowingCamera(sim.camera, robot, world)
        light = None
        if s.cell.light_port:
            light = _gardasoft(s.cell.light_port, s.cell)
        thermometer = None
        if s.cell.thermometer_port:
            from drivers.thermometer import FlukeReadout

            thermometer = FlukeReadout(s.cell.thermometer_port)
        d = Devices(robot=robot, camera=camera, light=light, world=world, thermometer=thermometer)
    else:
        raise InputError(f"unknown backend {backend!r} (use sim or ur)")
    for dev in (d.robot, d.camera, d.light, d.thermometer):
        if dev is not None:
            dev.connect()
            d._closers.append(dev.close)
    return d


def inject_unreachable(devices: Devices, job: LoadedJob, backend: str, joints_rad) -> None:
    """``[sim] unreachable_stations``: the controller refuses the moves to these joint targets ``(n, 6)``.

    The simulated robot takes them directly; with ``backend = "ur"`` they go to the loopback UR controller
    (``sim_backend.ur_controller``), which then refuses them as a real one refuses a target outside its
    safety limits. A real controller cannot be told: ``InputError``.
    """
    if backend == "sim":
        devices.robot.inject_unreachable(joints_rad)
        return
    from sim_backend.ur_controller import refuse_targets_at

    host = job.spec.cell.host
    try:
        refuse_targets_at(host, joints_rad)
    except (OSError, ValueError) as exc:
        raise InputError(f"[sim] unreachable_stations works with the simulated cell or the loopback UR controller "
                         f"only; the controller at {host} did not take it ({exc})") from None


FRAME_FAULTS_ENV = "CELL_SIM_FRAME_FAULTS"


def _frame_faults_from_env() -> dict[int, str]:
    """Faults of the simulated camera for this session (tests): ``CELL_SIM_FRAME_FAULTS='{"3": "missing"}'`` makes
    the 3rd capture of the session fail (``missing``, ``late``, ``duplicate``). A hardware fault, not part of the
    job: a resumed session without the variable has a mended camera."""
    import json

    text = os.environ.get(FRAME_FAULTS_ENV, "").strip()
    if not text:
        return {}
    try:
        doc = json.loads(text)
        faults = {int(k): str(v) for k, v in doc.items()}
    except (ValueError, AttributeError, TypeError):
        raise InputError(f"{FRAME_FAULTS_ENV}={text!r}: give a JSON object such as {{\"3\": \"missing\"}}") from None
    bad = sorted(set(faults.values()) - {"missing", "late", "duplicate"})
    if bad:
        raise InputError(f"{FRAME_FAULTS_ENV}: unknown fault(s) {bad}; use missing, late or duplicate")
    return faults


def _gardasoft(where: str, cell):
    """The Gardasoft RT controller at ``where``: a serial device path, or ``tcp://HOST[:PORT]`` (Ethernet models)."""
    from drivers.gardasoft import TCP_PORT, GardasoftRT

    kw = dict(channel=cell.light_channel, trigger_input=cell.light_input, brightness_pct=cell.light_brightness_pct)
    if where.startswith("tcp://"):
        host, _, port = where[len("tcp://"):].partition(":")
        return GardasoftRT(host=host, tcp_port=int(port) if port else TCP_PORT, **kw)
    return GardasoftRT(where, **kw)


class _FollowingCamera:
    """A simulated camera that renders from the pose a (real-driver) robot reports."""

    def __init__(self, camera, robot, world):
        self.camera, self.robot, self.world = camera, robot, world

    def connect(self) -> None:
        self.camera.connect()

    def close(self) -> None:
        self.camera.close()

    def capture(self):
        st = self.robot.state()
        self.world.set_robot(np.asarray(st.joints_rad), np.asarray(st.base_from_flange))
        return self.camera.capture()
