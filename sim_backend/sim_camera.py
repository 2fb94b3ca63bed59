"""SimCamera: renders the grey image that the camera at the robot's pose would see.

What is rendered (all from the world's *true* state):

* the part: a dim Lambertian shading lit by a ring light at the camera, from a coarse
  ray-cast depth/normal render (one ray per ``background_step_px`` block, bilinearly
  upsampled; cheap, and smooth under the targets);
* retro-reflective targets: flat discs of ``part.target_diameter_m`` in the plane of the
  target normal, projected exactly: every pixel corner is mapped through the camera's
  undistortion and intersected with the disc's plane, pixels near the rim are
  supersampled (``supersample`` x ``supersample`` area coverage); bright, with a retro
  gain that falls off as ``cos(incidence) ** falloff_exponent``;
* worn retro targets (the world's ``damage_kind`` etc., the job's ``[sim] damaged_targets``): a plain dot whose
  coating is lost beyond a chord (``edge``) or under a dark speck (``spot``) shows the target's non-reflective
  backing (``marker_black_level``) there: :func:`sim_backend.coverage.damaged_disc_coverage` gives the dot's
  whole area (alpha) and its still reflective part (white), exact to the supersampling along the chord and the
  speck's rim as along the dot's rim. Intact dots are drawn as before (bit for bit); coded targets are not
  damaged;
* coded targets: ArUco markers (``cv2.aruco.DICT_4X4_250``, 4x4 bits, one black border
  cell, one white quiet-zone cell around it) of side ``part.coded_size_m`` (black border's
  outer edge), axes as :func:`sim_backend.world.marker_axes`, textured by the same exact
  inverse mapping (which includes the lens distortion, so no ``warpPerspective`` is needed);
* occlusion by the part's mesh: rays from the camera to the centre and rim of each target
  (Embree); fully hidden targets are not rendered, partly hidden ones get a per-pixel
  visibility mask (and are listed as ``partial``);
* then a Gaussian lens blur (``blur_sigma_px``), and about each target the lens's defocus at its depth
  (``Sensor.with_depth_of_field``: a thin lens focused within the job's depth of field), photon (shot) and read
  noise, black level, clipping and quantisation to ``bit_depth`` bits (uint8, or uint16 above 8 bits).

Image-plane jitter: ``image_sigma_px`` (the job's ``[sim] image_sigma_px``) displaces each
rendered target's whole image by an independent N(0, sigma^2) offset per image and axis,
modelling what is not rendered (print defects, uneven lighting, vibration). Zero by default.

``Frame.meta["sim_truth"]`` carries the true pose and projections: for tests only; the cell
must never use it to measure.
"""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from calibration.camera import invert, project
from calibration.errors import CalibrationError, DriverError, InputError, NotConnectedError
from drivers.protocols import Frame
from sim_backend.coverage import (  # noqa: F401  (re-exported: the kernels lived here)
    _MARKER_CELLS,
    _QUIET_CELLS,
    ARUCO_DICTIONARY,
    UndistortionLattice,
    _plane_coords,
    aruco_texture,
    damaged_disc_coverage,
    disc_coverage,
    marker_coverage,
    ring_coverage,
)
from sim_backend.world import World, marker_axes

__all__ = [
    "ARUCO_DICTIONARY",
    "Photometry",
    "Sensor",
    "RenderOptions",
    "UndistortionLattice",
    "aruco_texture",
    "damaged_disc_coverage",
    "disc_coverage",
    "marker_coverage",
    "ring_coverage",
    "apply_sensor",
    "SimCamera",
]



@dataclass(frozen=True)
class Photometry:
    """Scene brightness as fractions of the sensor's full scale, at ``reference_exposure_s``,
    ``reference_distance_m``, full light and normal incidence."""

    retro_level: float = 0.70
    part_level: float = 0.08
    ambient_level: float = 0.005
    marker_black_level: float = 0.03
    falloff_exponent: float = 2.0
    max_incidence_rad: float = math.radians(85.0)
    reference_distance_m: float = 0.7
    reference_exposure_s: float = 0.002


@dataclass(frozen=True)
class Sensor:
    """Sensor and lens: ``full_well_e`` electrons = full scale at unit gain; noise off gives a clean image.

    ``gain``: the analog gain (linear; a GenICam ``Gain`` of G dB is ``10 ** (G / 20)``). It multiplies the
    electrons' signal and their photon and read noise alike before the converter, so the image is brighter, clips
    sooner and is no less noisy relative to its light: it does not add information.
    """

    bit_depth: int = 8
    full_well_e: float = 10000.0
    read_noise_e: float = 10.0
    black_level: float = 0.01
    blur_sigma_px: float = 0.7
    noise: bool = True
    gain: float = 1.0
    focus_m: float = 0.0
    defocus_px_m: float = 0.0

    def __post_init__(self) -> None:
        if not 8 <= self.bit_depth <= 16:
            raise InputError(f"sensor bit_depth must be 8..16, got {self.bit_depth}")
        if not (np.isfinite(self.gain) and self.gain > 0):
            raise InputError(f"sensor gain must be a positive number, got {self.gain}")

    def with_camera(self, pixel_format: str = "Mono8", gain_db: float | None = None) -> "Sensor":
        """This sensor read out as a GenICam camera set to ``pixel_format`` (its bit depth: ``Mono12`` gives
        12-bit images in 16-bit words) and ``Gain`` ``gain_db`` (None: unit gain, the camera's own)."""
        from dataclasses import replace

        from drivers.pixels import PixelFormatUnsupported, bit_depth

        try:
            bits = bit_depth(pixel_format)
        except PixelFormatUnsupported as e:
            raise InputError(f"simulated camera: {e}") from e
        return replace(self, bit_depth=bits, gain=1.0 if gain_db is None else float(10.0 ** (gain_db / 20.0)))

    def with_depth_of_field(self, near_m: float, far_m: float, coc_px: float) -> "Sensor":
        """This sensor behind a lens focused for the depth of field ``near_m .. far_m`` (the job's ``[camera] near /
        far``) where the blur circle is ``coc_px`` pixels across at either limit (0: every depth sharp).

        A thin lens's blur circle is ``A f / pitch * |1/z - 1/z_f|`` pixels across for a point at depth ``z`` (``A``
        the aperture's diameter): it is proportional to the defocus in dioptres. The depth of field's limits then fix
        the focus, ``1/z_f = (1/near + 1/far) / 2``, and the aperture, ``A f / pitch = coc_px / (1/near - 1/z_f)``.
        """
        from dataclasses import replace

        if coc_px < 0 or not 0 < near_m < far_m:
            raise InputError(f"depth of field: need 0 < near < far and a circle of confusion >= 0, got near {near_m} m, "
                             f"far {far_m} m, {coc_px} px")
        if coc_px == 0:
            return replace(self, focus_m=0.0, defocus_px_m=0.0)
        dioptre = 0.5 * (1.0 / near_m + 1.0 / far_m)
        return replace(self, focus_m=1.0 / dioptre, defocus_px_m=coc_px / (1.0 / near_m - dioptre))

    def defocus_sigma_px(self, depth_m: np.ndarray) -> np.ndarray:
        """The defocus blur of points at camera depth ``depth_m``, as a Gaussian's sigma (px): a uniform blur circle of
        diameter ``b`` has an sd of ``b / 4`` along each axis. It adds in quadrature to ``blur_sigma_px``."""
        d = np.asarray(depth_m, dtype=float)
        if self.defocus_px_m <= 0:
            return np.zeros_like(d)
        return 0.25 * self.defocus_px_m * np.abs(1.0 / np.maximum(d, 1e-6) - 1.0 / self.focus_m)

    def with_noise_scale(self, scale: float) -> "Sensor":
        """This sensor with its photon and read noise scaled by ``scale`` (0: no noise).

        A pixel's relative noise is sqrt(x * full_well + read^2) / full_well, so full well / scale^2 and
        read noise / scale scale it by ``scale`` at every signal level.
        """
        from dataclasses import replace

        if scale < 0:
            raise InputError(f"sensor noise scale must be >= 0, got {scale}")
        if scale == 0:
            return replace(self, noise=False)
        return replace(self, full_well_e=self.full_well_e / scale**2, read_noise_e=self.read_noise_e / scale)


@dataclass(frozen=True)
class RenderOptions:
    """How the image is computed (not what the scene is)."""

    supersample: int = 8
    adaptive: bool = True  # supersample only the pixels that the rim/edges cross
    background_step_px: int = 8
    lattice_step_px: float = 4.0
    occlusion_rim_samples: int = 8
    occlusion_tolerance_m: float = 5e-4
    image_sigma_px: float = 0.0
    window_margin_px: int = 2


def apply_sensor(img: np.ndarray, sensor: Sensor, rng: np.random.Generator | None, *,
                 block_rows: int = 32) -> np.ndarray:
    """Blurred irradiance ``img: (h, w)`` (fraction of full scale) -> quantised sensor image.

    Adds the black level, photon noise (Gaussian approximation of Poisson, variance = electrons)
    and read noise when ``sensor.noise`` (then ``rng`` is required), clips and rounds.
    Returns (h, w) uint8 for 8 bits, uint16 otherwise.

    The image is processed ``block_rows`` rows at a time (issue 21): each block's few passes stay in
    the cache instead of streaming the whole 5 MP image through memory once per pass. The normal
    variates are drawn block after block from one stream seeded from ``rng`` (what
    :func:`standard_normal_image` gives for the whole image), so the result does not depend on the
    block size.
    """
    full = float(2**sensor.bit_depth - 1)
    x = np.asarray(img, dtype=np.float32)
    if sensor.noise and rng is None:
        raise ValueError("apply_sensor with noise needs an rng")
    fast8 = sensor.bit_depth == 8 and x.ndim == 2
    out = np.empty(x.shape, dtype=np.uint8 if sensor.bit_depth == 8 else np.uint16)
    if sensor.noise:
        cv2.setRNGSeed(_noise_seed(rng))
    rows = max(int(block_rows), 1)
    shape = (min(rows, x.shape[0]),) + x.shape[1:]
    e, sigma, z = (np.empty(shape, dtype=np.float32) for _ in range(3))
    for r0 in range(0, x.shape[0], rows):
        xb = x[r0 : r0 + rows]
        n = len(xb)
        eb = e[:n]
        if sensor.noise:
            sb, zb = sigma[:n], z[:n]
            np.maximum(xb, np.float32(0.0), out=eb)
            eb *= np.float32(sensor.full_well_e)  # electrons
            np.add(eb, np.float32(sensor.read_noise_e**2), out=sb)
            np.sqrt(sb, out=sb)
            cv2.randn(zb, 0.0, 1.0)
            sb *= zb
            eb += sb
            eb *= np.float32(full * sensor.gain / sensor.full_well_e)
            eb += np.float32(sensor.black_level * full)
        else:
            np.multiply(xb, np.float32(sensor.gain), out=eb)
            eb += np.float32(sensor.black_level)
            eb *= np.float32(full)
        np.maximum(eb, np.float32(0.0), out=eb)
        if fast8:  # saturating round (half to even, as np.rint) in one pass
            cv2.convertScaleAbs(eb, dst=out[r0 : r0 + n])
        else:
            np.minimum(eb, np.float32(full), out=eb)
            np.rint(eb, out=eb)
            out[r0 : r0 + n] = eb
    return out


def _noise_seed(rng: np.random.Generator) -> int:
    """OpenCV's random stream seed for one image, drawn from ``rng``."""
    return int(rng.integers(1, 2**31 - 1))


def standard_normal_image(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """(h, w) float32 independent N(0, 1) variates, reproducible from ``rng``.

    OpenCV's table (ziggurat) normal generator, seeded from ``rng``, is ~3x faster than NumPy's for a
    5 MP image (issue 21: the noise was the render's largest cost); its random stream is the calling
    thread's, so the result depends only on ``rng``'s state.
    """
    out = np.empty(shape, dtype=np.float32)
    cv2.setRNGSeed(_noise_seed(rng))
    cv2.randn(out, 0.0, 1.0)
    return out


# --- the scene ---------------------------------------------------------------------


@dataclass
class _Visible:
    """Targets selected for rendering in one image."""

    index: np.ndarray  # (m,) target indices
    partial: np.ndarray  # (m,) bool: partly occluded
    occluded: np.ndarray  # indices of targets in view but fully hidden
    truncated: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    # set as the targets are drawn: each one's pixel window (u0, v0, w, h) and its camera depth (m), for the defocus
    windows: tuple | None = None
    depth: np.ndarray | None = None


class SimCamera:
    """A camera in the simulated world; satisfies ``drivers.protocols.Camera``.

    Args:
        world: the simulated world (its true pose, part and intrinsics are used).
        photometry, sensor, options: see the dataclasses above.
        rng: random stream for noise and jitter (default: a child stream of the world's seed).
        exposure_s: exposure time; brightness scales with it.
        coded_family: how the coded targets look: "aruco" (DICT_4X4_250 markers of side
            ``part.coded_size_m``) or a ring-code family (``calibration.ringcodes.RING_FAMILIES``:
            a centre dot of the part's target diameter inside its code ring).
    """

    def __init__(
        self,
        world: World,
        *,
        photometry: Photometry = Photometry(),
        sensor: Sensor = Sensor(),
        options: RenderOptions = RenderOptions(),
        rng: np.random.Generator | None = None,
        exposure_s: float = 0.002,
        coded_family: str = "aruco",
    ) -> None:
        self.world = world
        self.coded_family = coded_family
        self.photometry = photometry
        self.sensor = sensor
        self.options = options
        self.rng = world.spawn_rng() if rng is None else rng
        self.exposure_s = float(exposure_s)
        self.intr = world.intrinsics
        self.lattice = UndistortionLattice(self.intr, options.lattice_step_px)
        self._bg_rays = self._background_rays()
        self._connected = False
        self._fail_captures = 0
        self._frame_id = 0
        self._captures = 0
        self._frame_faults: dict[int, str] = {}
        self._last_frame: Frame | None = None
        self.late_frame_s = 1.0
        self.strobe_out = None  # called as each exposure starts: the strobe line, wired e.g. to a light controller
        self._lock = threading.Lock()
        targets = world.part.targets
        self._coded = np.asarray(targets.kind) == "coded"
        codes = np.asarray(targets.code)[self._coded]
        if coded_family == "aruco":
            self._textures = {int(c): aruco_texture(int(c)) for c in codes}
        else:
            from calibration.ringcodes import code_bits, ring_family

            try:
                self._ring_family = ring_family(coded_family)
                self._textures = {int(c): code_bits(coded_family, int(c)) for c in codes}
            except CalibrationError as e:
                raise InputError(f"sim camera: {e}") from None

    # --- Camera protocol ---------------------------------------------------
    def connect(self) -> None:
        self._connected = True

    def close(self) -> None:
        self._connected = False

    def capture(self) -> Frame:
        """Render, expose and quantise one image at the world's current true pose."""
        with self._lock:
            if not self._connected:
                raise NotConnectedError("sim camera: not connected; call connect() first")
            self._captures += 1
            fault = self._frame_faults.pop(self._captures, None)
            if self._fail_captures or fault == "missing":
                self._fail_captures = max(0, self._fail_captures - (fault != "missing"))
                raise DriverError("sim camera: frame timeout (injected fault); retry the capture")
            if fault == "duplicate" and self._last_frame is not None:
                return self._last_frame  # the previous frame delivered again (a double trigger, a stale buffer)
            triggered = time.time()
            if self.strobe_out is not None:
                self.strobe_out()  # the camera's strobe output goes high as the exposure starts
            image, truth = self.render()
            if fault == "late":
                time.sleep(self.late_frame_s)
            self._frame_id += 1
            meta = {
                "frame_id": self._frame_id,
                "device": "sim",
                "bit_depth": self.sensor.bit_depth,
                "triggered_host_s": triggered,
                "sim_truth": truth,
            }
            self._last_frame = Frame(image=image, timestamp_s=time.time(), exposure_s=self.exposure_s, meta=meta)
            return self._last_frame

    # --- fault injection -----------------------------------------------------
    def inject_capture_failure(self, n: int = 1) -> None:
        """The next ``n`` captures raise ``DriverError`` (a frame timeout)."""
        self._fail_captures += int(n)

    def inject_frame_faults(self, faults: dict[int, str], late_s: float = 1.0) -> None:
        """Faults by capture number (1 = the first capture after this call): ``"missing"`` (no frame: a
        timeout), ``"late"`` (the frame comes ``late_s`` after its exposure), ``"duplicate"`` (the previous
        frame is delivered again)."""
        bad = {k: v for k, v in faults.items() if v not in ("missing", "late", "duplicate")}
        if bad:
            raise ValueError(f"unknown frame faults {bad}")
        self._frame_faults = {self._captures + int(k): v for k, v in faults.items()}
        self.late_frame_s = float(late_s)

    def inject_disconnect(self) -> None:
        """The connection drops: captures raise ``NotConnectedError`` until ``connect()``."""
        self._connected = False

    # --- rendering ---------------------------------------------------------------
    def render(self, part_from_cam: np.ndarray | None = None, *, noise: bool | None = None, quantise: bool = True):
        """Render the image seen from ``part_from_cam`` (default: the world's true camera pose).

        Returns ``(image, truth)``: the quantised image (or, with ``quantise=False``, the
        blurred noise-free irradiance as float32 fractions of full scale) and a dict of the
        true pose, ids, kinds and projections of the rendered targets.
        """
        if part_from_cam is None:
            part_from_cam = self.world.true_part_from_cam()
        part_from_cam = np.asarray(part_from_cam, dtype=float)
        cam_from_part = invert(part_from_cam)
        ph, opt = self.photometry, self.options
        light = float(self.world.light_fraction) * self.exposure_s / ph.reference_exposure_s
        img = self._render_background(part_from_cam, light)
        vis = self._select(part_from_cam, cam_from_part)
        targets = self.world.part.targets
        xyz = self.world.true_xyz
        ids = np.asarray(targets.ids)
        shift = np.zeros((len(vis.index), 2))
        if opt.image_sigma_px > 0 and len(vis.index):
            shift = opt.image_sigma_px * self.rng.standard_normal((len(vis.index), 2))
        self._draw_targets(img, vis, cam_from_part, shift, light)
        if self.sensor.blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), self.sensor.blur_sigma_px, borderType=cv2.BORDER_REFLECT)
        if self.sensor.defocus_px_m > 0 and len(vis.index):
            img = self._defocus(img, vis)
        uv = project(self.intr, cam_from_part, xyz[vis.index]) if len(vis.index) else np.zeros((0, 2))
        coded = self._coded[vis.index]
        corners_uv = {}
        if coded.any() and self.coded_family == "aruco":
            corners = self.world.true_marker_corners()[vis.index[coded]]
            cuv = project(self.intr, cam_from_part, corners.reshape(-1, 3)).reshape(-1, 4, 2)
            corners_uv = {str(i): c.tolist() for i, c in zip(ids[vis.index[coded]], cuv)}
        truth = {
            "part_from_cam": part_from_cam.tolist(),
            "ids": ids[vis.index].tolist(),
            "kind": np.asarray(targets.kind)[vis.index].tolist(),
            "uv": uv.tolist(),
            "shift_px": shift.tolist(),
            "partial_ids": ids[vis.index[vis.partial]].tolist(),
            "occluded_ids": ids[vis.occluded].tolist(),
            "truncated_ids": ids[vis.truncated].tolist(),
            "damaged_ids": ids[vis.index[self.world.damage_kind[vis.index] != 0]].tolist(),
            "marker_corners_uv": corners_uv,
        }
        if not quantise:
            return img, truth
        use_noise = self.sensor.noise if noise is None else noise
        sensor = self.sensor if use_noise == self.sensor.noise else _with_noise(self.sensor, use_noise)
        return apply_sensor(img, sensor, self.rng), truth

    def _background_rays(self) -> tuple[np.ndarray, tuple[int, int]]:
        intr, s = self.intr, self.options.background_step_px
        gw, gh = int(math.ceil(intr.width / s)), int(math.ceil(intr.height / s))
        u = (np.arange(gw) + 0.5) * intr.width / gw - 0.5
        v = (np.arange(gh) + 0.5) * intr.height / gh - 0.5
        uu, vv = np.meshgrid(u, v)
        xy = intr.pixel_to_normalised(np.stack([uu, vv], axis=-1).reshape(-1, 2))
        return np.column_stack([xy, np.ones(len(xy))]), (gh, gw)

    def _render_background(self, part_from_cam: np.ndarray, light: float) -> np.ndarray:
        """Dim Lambertian part under the ring light, (h, w) float32 fraction of full scale; the ambient light is
        continuous, so the exposure time scales it as it scales the ring light, which the light switch does not."""
        ph, intr = self.photometry, self.intr
        rays, (gh, gw) = self._bg_rays
        d = rays @ part_from_cam[:3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        dist, tri = self.world.first_hit(part_from_cam[:3, 3], d)
        shade = np.full(len(d), float(ph.ambient_level * self.exposure_s / ph.reference_exposure_s))
        hit = tri >= 0
        if hit.any():
            n = np.asarray(self.world.scene_mesh.face_normals)[tri[hit]]
            cos = np.abs(np.sum(n * d[hit], axis=1))
            shade[hit] += light * ph.part_level * cos * (ph.reference_distance_m / dist[hit]) ** 2
        small = shade.reshape(gh, gw).astype(np.float32)
        return cv2.resize(small, (intr.width, intr.height), interpolation=cv2.INTER_LINEAR)

    def _select(self, part_from_cam: np.ndarray, cam_from_part: np.ndarray) -> _Visible:
        """Targets in front, facing the camera, in the image, and not fully occluded."""
        w = self.world
        xyz, nrm = w.true_xyz, w.normals
        C = part_from_cam[:3, 3]
        to_cam = C - xyz
        dist = np.linalg.norm(to_cam, axis=1)
        cos_inc = np.sum(nrm * to_cam, axis=1) / dist
        Xc = xyz @ cam_from_part[:3, :3].T + cam_from_part[:3, 3]
        cand = np.nonzero((Xc[:, 2] > 0.01) & (cos_inc > math.cos(self.photometry.max_incidence_rad)))[0]
        if len(cand):
            reach = self._extent(cand) / Xc[cand, 2] * max(self.intr.fx_px, self.intr.fy_px)
            uv = project(self.intr, cam_from_part, xyz[cand])
            ok = np.isfinite(uv).all(axis=1) & self.intr.in_image(uv, margin_px=-reach - 2)
            cand = cand[ok]
        # occlusion: centre + rim samples
        m = self.options.occlusion_rim_samples
        ang = 2 * np.pi * np.arange(m) / m
        e1, e2 = marker_axes(nrm[cand])
        rim = 0.95 * self._extent(cand)[:, None, None] * (np.cos(ang)[None, :, None] * e1[:, None] + np.sin(ang)[None, :, None] * e2[:, None])
        pts = np.concatenate([xyz[cand][:, None], xyz[cand][:, None] + rim], axis=1)  # (c, m+1, 3)
        dirs = pts.reshape(-1, 3) - C
        hit, _ = w.first_hit(C, dirs)
        tol = self.options.occlusion_tolerance_m + np.linalg.norm(w.deviations[cand], axis=1)
        seen = (hit.reshape(len(cand), m + 1) >= np.linalg.norm(dirs, axis=1).reshape(len(cand), m + 1) - tol[:, None])
        n_seen = seen.sum(axis=1)
        keep = n_seen > 0
        return _Visible(index=cand[keep], partial=n_seen[keep] < m + 1, occluded=cand[~keep])

    def _extent(self, idx: np.ndarray) -> np.ndarray:
        """(k,) in-plane radius (m) of targets ``idx``: disc radius, or half the patch diagonal."""
        part = self.world.part
        if self.coded_family != "aruco":
            return np.where(self._coded[idx], self._ring_family.quiet, 1.0) * 0.5 * part.target_diameter_m
        half_patch = 0.5 * part.coded_size_m * (_MARKER_CELLS + 2 * _QUIET_CELLS) / _MARKER_CELLS * math.sqrt(2)
        return np.where(self._coded[idx], half_patch, 0.5 * part.target_diameter_m)

    def _windows(self, idx: np.ndarray, cam_from_part: np.ndarray, shift: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Pixel windows (u0, v0, w, h) that hold each target's image, (k,) ints each."""
        xyz, nrm = self.world.true_xyz[idx], self.world.normals[idx]
        e1, e2 = marker_axes(nrm)
        m = 24
        ang = 2 * np.pi * np.arange(m) / m
        r = self._extent(idx)[:, None, None]
        rim = xyz[:, None] + r * (np.cos(ang)[None, :, None] * e1[:, None] + np.sin(ang)[None, :, None] * e2[:, None])
        uv = project(self.intr, cam_from_part, rim.reshape(-1, 3)).reshape(len(idx), m, 2) + shift[:, None]
        mg = self.options.window_margin_px
        lo = np.floor(uv.min(axis=1)).astype(int) - mg
        hi = np.ceil(uv.max(axis=1)).astype(int) + mg
        return lo[:, 0], lo[:, 1], hi[:, 0] - lo[:, 0] + 1, hi[:, 1] - lo[:, 1] + 1

    def _draw_targets(self, img: np.ndarray, vis: _Visible, cam_from_part: np.ndarray, shift: np.ndarray, light: float) -> None:
        if not len(vis.index):
            return
        w, ph, opt = self.world, self.photometry, self.options
        idx = vis.index
        R, t = cam_from_part[:3, :3], cam_from_part[:3, 3]
        centre_c = w.true_xyz[idx] @ R.T + t
        e1, e2 = marker_axes(w.normals[idx])
        n_c, e1_c, e2_c = w.normals[idx] @ R.T, e1 @ R.T, e2 @ R.T
        dist = np.linalg.norm(centre_c, axis=1)
        cos_inc = np.clip(-np.sum(n_c * centre_c, axis=1) / dist, 0.0, 1.0)
        illum = light * (ph.reference_distance_m / dist) ** 2
        level = ph.retro_level * illum * cos_inc**ph.falloff_exponent
        black = ph.marker_black_level * illum * cos_inc
        u0, v0, ww, hh = self._windows(idx, cam_from_part, shift)
        vis.windows, vis.depth = (u0, v0, ww, hh), centre_c[:, 2]
        H, W = img.shape
        truncated = (u0 < 0) | (v0 < 0) | (u0 + ww > W) | (v0 + hh > H)
        vis.truncated = idx[truncated]
        coded = self._coded[idx]
        # one vectorised call per group of equal (bucketed) window size and kind
        bw, bh = 8 * np.ceil(ww / 8).astype(int), 8 * np.ceil(hh / 8).astype(int)
        for is_coded in (False, True):
            sel_kind = coded == is_coded
            for gw_, gh_ in sorted(set(zip(bw[sel_kind], bh[sel_kind]))):
                g = np.nonzero(sel_kind & (bw == gw_) & (bh == gh_))[0]
                args = (self.lattice, u0[g], v0[g], gh_, gw_, centre_c[g], n_c[g], e1_c[g], e2_c[g])
                if is_coded and self.coded_family != "aruco":
                    bits = np.stack([self._textures[int(c)] for c in np.asarray(w.part.targets.code)[idx[g]]])
                    alpha, white = ring_coverage(*args, 0.5 * float(w.part.target_diameter_m), bits, self._ring_family,
                                                 shift[g], opt.supersample, opt.adaptive)
                elif is_coded:
                    tex = np.stack([self._textures[int(c)] for c in np.asarray(w.part.targets.code)[idx[g]]])
                    alpha, white = marker_coverage(*args, float(w.part.coded_size_m), tex, shift[g], opt.supersample, opt.adaptive)
                else:
                    radius = 0.5 * float(w.part.target_diameter_m)
                    alpha = disc_coverage(*args, radius, shift[g], opt.supersample, opt.adaptive)
                    white = alpha
                    hurt = np.flatnonzero(w.damage_kind[idx[g]] != 0)
                    if len(hurt):  # worn dots: their reflective part (intact ones keep the call above, bit for bit)
                        gd, kd = g[hurt], idx[g[hurt]]
                        ad, wd = damaged_disc_coverage(self.lattice, u0[gd], v0[gd], gh_, gw_, centre_c[gd], n_c[gd],
                                                       e1_c[gd], e2_c[gd], radius, w.damage_kind[kd],
                                                       w.damage_lost[kd], w.damage_dir_rad[kd], w.damage_offset[kd],
                                                       shift[gd], opt.supersample, opt.adaptive)
                        alpha, white = alpha.copy(), alpha.copy()
                        alpha[hurt], white[hurt] = ad, wd
                for j, k in enumerate(g):
                    a, wh = alpha[j], white[j]
                    if vis.partial[k]:
                        vm = self._visibility_mask(u0[k], v0[k], gh_, gw_, idx[k], cam_from_part, shift[k])
                        a, wh = a * vm, wh * vm
                    self._compose(img, u0[k], v0[k], a, wh, level[k], black[k])

    def _defocus(self, img: np.ndarray, vis: _Visible) -> np.ndarray:
        """Each target's window blurred further by the lens's defocus at the target's depth
        (:meth:`Sensor.defocus_sigma_px`; Gaussian blurs compose in quadrature). The window is the target's image with
        its ground around it, at about its depth; the part's shading elsewhere is smooth and keeps the lens's blur."""
        extra = self.sensor.defocus_sigma_px(vis.depth)  # the windows and depths _draw_targets found
        u0, v0, ww, hh = vis.windows
        out = img.copy()
        H, W = img.shape
        for k in np.flatnonzero(extra > 0.02):
            pad = int(math.ceil(3.0 * extra[k])) + 1
            a0, b0 = max(u0[k] - 2 * pad, 0), max(v0[k] - 2 * pad, 0)  # read: the window and twice the blur's reach
            a1, b1 = min(u0[k] + ww[k] + 2 * pad, W), min(v0[k] + hh[k] + 2 * pad, H)
            if a1 <= a0 or b1 <= b0:
                continue
            blurred = _blur_by_variance(img[b0:b1, a0:a1], float(extra[k]) ** 2)
            c0, d0 = max(u0[k] - pad, 0), max(v0[k] - pad, 0)  # write: the window and the blur's reach
            c1, d1 = min(u0[k] + ww[k] + pad, W), min(v0[k] + hh[k] + pad, H)
            if c1 <= c0 or d1 <= d0:  # a window off the image's top or left edge but for its blur's reach: a negative
                continue  # end would count from the image's other side (a generated plate's dot did, at v0 = -27)
            out[d0:d1, c0:c1] = blurred[d0 - b0 : d1 - b0, c0 - a0 : c1 - a0]
        return out

    def _visibility_mask(self, u0: int, v0: int, h: int, w: int, target: int, cam_from_part: np.ndarray, shift: np.ndarray) -> np.ndarray:
        """(h, w) 1 where the ray through the pixel centre reaches the target's plane unoccluded."""
        part_from_cam = invert(cam_from_part)
        xy = self.lattice.on_grid((u0 + np.arange(w) - shift[0])[None], (v0 + np.arange(h) - shift[1])[None]).reshape(-1, 2)
        d = np.column_stack([xy, np.ones(len(xy))]) @ part_from_cam[:3, :3].T
        C = part_from_cam[:3, 3]
        P0, n = self.world.true_xyz[target], self.world.normals[target]
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = np.sum((P0 - C) * n) / (d @ n)
        reach = lam * np.linalg.norm(d, axis=1)
        hit, _ = self.world.first_hit(C, d)
        tol = self.options.occlusion_tolerance_m + np.linalg.norm(self.world.deviations[target])
        return (hit >= reach - tol).reshape(h, w).astype(float)

    @staticmethod
    def _compose(img: np.ndarray, u0: int, v0: int, alpha: np.ndarray, white: np.ndarray, level: float, black: float) -> None:
        H, W = img.shape
        h, w = alpha.shape
        a0, b0 = max(u0, 0), max(v0, 0)
        a1, b1 = min(u0 + w, W), min(v0 + h, H)
        if a1 <= a0 or b1 <= b0:
            return
        al = alpha[b0 - v0 : b1 - v0, a0 - u0 : a1 - u0]
        wh = white[b0 - v0 : b1 - v0, a0 - u0 : a1 - u0]
        patch = img[b0:b1, a0:a1]
        patch[...] = patch * (1 - al) + wh * level + (al - wh) * black


def _blur_by_variance(img: np.ndarray, var_px2: float) -> np.ndarray:
    """``img`` convolved with a separable kernel whose variance is ``var_px2`` along each axis: the three taps
    ``[v/2, 1 - v, v/2]`` below 0.49 px^2 (a Gaussian sampled at the pixels has a smaller variance than its sigma^2
    there: 0.215 for sigma 0.5), a sampled Gaussian above (within 0.3 % of its sigma^2 from sigma 0.7)."""
    if var_px2 < 0.49:
        k = np.array([0.5 * var_px2, 1.0 - var_px2, 0.5 * var_px2], dtype=np.float32)
        return cv2.sepFilter2D(img, -1, k, k, borderType=cv2.BORDER_REFLECT)
    return cv2.GaussianBlur(img, (0, 0), math.sqrt(var_px2), borderType=cv2.BORDER_REFLECT)


def _with_noise(sensor: Sensor, noise: bool) -> Sensor:
    from dataclasses import replace

    return replace(sensor, noise=noise)
