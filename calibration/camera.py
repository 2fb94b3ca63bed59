"""The one camera model of the cell.

Conventions (used by every package):

* Pose: ``cam_from_part`` is a 4x4 rigid transform, ``X_cam = R @ X_part + t``.
  The camera looks along its +z axis, x to the right of the image, y down
  (the OpenCV / pycolmap convention).
* Pixels: ``u = fx * x/z + cx``, ``v = fy * y/z + cy`` (before distortion is
  applied to the normalised coordinates). The origin is the centre of the
  top-left pixel, so an image ``width`` pixels wide spans ``u`` in
  ``[-0.5, width - 0.5]``.
* Distortion: Brown's model on normalised coordinates, radial ``k1, k2, k3``
  and tangential ``p1, p2`` (the same parameters as OpenCV's ``distCoeffs``
  ``(k1, k2, p1, p2, k3)``).
* Pose perturbation for Jacobians: ``cam_from_part' = Exp(xi) @ cam_from_part``
  with ``xi = (omega, tau)`` (rotation vector first, then translation), so that
  ``dX_cam = -[X_cam]x omega + tau``.

The seed paper writes the projective model as ``M = K [R | T]`` (eq. 1-2) with
``alpha_u = -K_u f``; we use positive focal lengths in pixels (``fx = f / pixel
size``), an image y axis pointing down, and the equivalent collinearity form
``X_cam = R (P - Pc)`` with ``Pc = -R^T T`` (eq. 3-5).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from calibration.errors import CalibrationError

__all__ = [
    "Intrinsics",
    "project",
    "project_with_jacobians",
    "to_camera",
    "projection_matrix",
    "decompose_projection_matrix",
    "collinearity_from_pose",
    "pose_from_collinearity",
    "invert",
    "make_pose",
    "look_at",
    "skew",
    "exp_se3",
]


@dataclass(frozen=True)
class Intrinsics:
    """Interior orientation of a camera.

    Attributes:
        fx_px, fy_px: focal length in pixels along u and v.
        cx_px, cy_px: principal point in pixels (origin: centre of the top-left pixel).
        width, height: image size in pixels.
        k1, k2, k3: Brown radial distortion (on normalised coordinates).
        p1, p2: Brown tangential distortion.
        pixel_size_m: physical pixel pitch (metres), for reports; ``None`` if unknown.
    """

    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    width: int
    height: int
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    pixel_size_m: float | None = field(default=None, compare=False)

    @classmethod
    def from_focal_length(
        cls,
        focal_m: float,
        pixel_size_m: float,
        width: int,
        height: int,
        *,
        cx_px: float | None = None,
        cy_px: float | None = None,
        aspect: float = 1.0,
        **distortion: float,
    ) -> "Intrinsics":
        """Build from a lens focal length and the sensor's pixel pitch (metres)."""
        fx = focal_m / pixel_size_m
        return cls(
            fx_px=fx,
            fy_px=fx * aspect,
            cx_px=(width - 1) / 2.0 if cx_px is None else cx_px,
            cy_px=(height - 1) / 2.0 if cy_px is None else cy_px,
            width=int(width),
            height=int(height),
            pixel_size_m=pixel_size_m,
            **distortion,
        )

    @property
    def K(self) -> np.ndarray:
        """Calibration matrix, (3, 3)."""
        return np.array(
            [[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]]
        )

    @property
    def dist_coeffs(self) -> np.ndarray:
        """OpenCV ordering ``(k1, k2, p1, p2, k3)``, (5,)."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])

    @property
    def has_distortion(self) -> bool:
        return any(v != 0.0 for v in (self.k1, self.k2, self.k3, self.p1, self.p2))

    def without_distortion(self) -> "Intrinsics":
        return replace(self, k1=0.0, k2=0.0, k3=0.0, p1=0.0, p2=0.0)

    def in_image(self, uv: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """Whether pixel coordinates ``uv: (..., 2)`` lie inside the image by ``margin_px``."""
        uv = np.asarray(uv)
        u, v = uv[..., 0], uv[..., 1]
        return (
            (u >= -0.5 + margin_px)
            & (u <= self.width - 0.5 - margin_px)
            & (v >= -0.5 + margin_px)
            & (v <= self.height - 0.5 - margin_px)
        )

    def to_dict(self) -> dict:
        d = {
            "fx_px": self.fx_px,
            "fy_px": self.fy_px,
            "cx_px": self.cx_px,
            "cy_px": self.cy_px,
            "width": self.width,
            "height": self.height,
            "k1": self.k1,
            "k2": self.k2,
            "k3": self.k3,
            "p1": self.p1,
            "p2": self.p2,
        }
        if self.pixel_size_m is not None:
            d["pixel_size_m"] = self.pixel_size_m
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "Intrinsics":
        return cls(**{k: d[k] for k in d if k in cls.__dataclass_fields__})

    # --- distortion -------------------------------------------------------
    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Apply distortion to normalised coordinates ``xy: (n, 2)``."""
        if not self.has_distortion:
            return np.asarray(xy, dtype=float)
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        xd = x * radial + 2 * self.p1 * x * y + self.p2 * (r2 + 2 * x * x)
        yd = y * radial + self.p1 * (r2 + 2 * y * y) + 2 * self.p2 * x * y
        return np.stack([xd, yd], axis=-1)

    def distortion_jacobian(self, xy: np.ndarray) -> np.ndarray:
        """d(distorted)/d(normalised) at ``xy: (n, 2)``, (n, 2, 2)."""
        x, y = xy[..., 0], xy[..., 1]
        n = x.shape
        J = np.zeros(n + (2, 2))
        if not self.has_distortion:
            J[..., 0, 0] = 1.0
            J[..., 1, 1] = 1.0
            return J
        r2 = x * x + y * y
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        dradial_dr2 = self.k1 + 2 * self.k2 * r2 + 3 * self.k3 * r2 * r2
        J[..., 0, 0] = radial + 2 * x * x * dradial_dr2 + 2 * self.p1 * y + 6 * self.p2 * x
        J[..., 0, 1] = 2 * x * y * dradial_dr2 + 2 * self.p1 * x + 2 * self.p2 * y
        J[..., 1, 0] = 2 * x * y * dradial_dr2 + 2 * self.p1 * x + 2 * self.p2 * y
        J[..., 1, 1] = radial + 2 * y * y * dradial_dr2 + 6 * self.p1 * y + 2 * self.p2 * x
        return J

    def undistort(self, xy_d: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Invert :meth:`distort` on normalised coordinates by Gauss-Newton, (n, 2)."""
        xy_d = np.asarray(xy_d, dtype=float)
        if not self.has_distortion:
            return xy_d.copy()
        xy = xy_d.copy()
        for _ in range(iterations):
            r = self.distort(xy) - xy_d
            J = self.distortion_jacobian(xy)
            xy = xy - np.linalg.solve(J, r[..., None])[..., 0]
            if np.max(np.abs(r), initial=0.0) < 1e-14:
                break
        return xy

    def pixel_to_normalised(self, uv: np.ndarray) -> np.ndarray:
        """Undistorted normalised image coordinates of pixels ``uv: (n, 2)``."""
        uv = np.asarray(uv, dtype=float)
        xy_d = np.stack(
            [(uv[..., 0] - self.cx_px) / self.fx_px, (uv[..., 1] - self.cy_px) / self.fy_px],
            axis=-1,
        )
        return self.undistort(xy_d)


# --- rigid transforms ------------------------------------------------------


def skew(w: np.ndarray) -> np.ndarray:
    """Cross-product matrices of ``w: (..., 3)``, (..., 3, 3)."""
    w = np.asarray(w, dtype=float)
    S = np.zeros(w.shape[:-1] + (3, 3))
    S[..., 0, 1] = -w[..., 2]
    S[..., 0, 2] = w[..., 1]
    S[..., 1, 0] = w[..., 2]
    S[..., 1, 2] = -w[..., 0]
    S[..., 2, 0] = -w[..., 1]
    S[..., 2, 1] = w[..., 0]
    return S


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 transform from a rotation (3, 3) and a translation (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms ``T: (..., 4, 4)``."""
    T = np.asarray(T, dtype=float)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def exp_se3(xi: np.ndarray) -> np.ndarray:
    """Left perturbation ``Exp(xi)`` for ``xi = (omega, tau)``, (4, 4).

    Rotation by the rotation vector ``omega`` and translation ``tau`` (applied after
    the rotation), matching the Jacobian convention of :func:`project_with_jacobians`
    to first order.
    """
    xi = np.asarray(xi, dtype=float)
    return make_pose(Rotation.from_rotvec(xi[:3]).as_matrix(), xi[3:])


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0), roll_rad: float = 0.0) -> np.ndarray:
    """``part_from_cam`` for a camera at ``eye`` whose +z axis points at ``target``.

    The image's "up" (-y) follows ``up`` as closely as possible, then the camera is
    rolled by ``roll_rad`` about its optical axis. Returns (4, 4).
    """
    eye = np.asarray(eye, dtype=float)
    z = np.asarray(target, dtype=float) - eye
    z = z / np.linalg.norm(z)
    up = np.asarray(up, dtype=float)
    if abs(np.dot(z, up / np.linalg.norm(up))) > 0.999:
        up = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1)
    if roll_rad:
        R = R @ Rotation.from_rotvec([0.0, 0.0, roll_rad]).as_matrix()
    return make_pose(R, eye)


# --- projection --------------------------------------------------------------


def to_camera(cam_from_part: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points ``(n, 3)`` in the part frame to the camera frame, (n, 3)."""
    T = np.asarray(cam_from_part, dtype=float)
    return np.asarray(points, dtype=float) @ T[:3, :3].T + T[:3, 3]


def project(intr: Intrinsics, cam_from_part: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Pixel coordinates of ``points: (n, 3)`` (part frame), (n, 2).

    Points behind the camera give ``nan``.
    """
    Xc = to_camera(cam_from_part, points)
    z = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = Xc[:, :2] / z[:, None]
    xy[z <= 0] = np.nan
    xy = intr.distort(xy)
    return np.stack([intr.fx_px * xy[:, 0] + intr.cx_px, intr.fy_px * xy[:, 1] + intr.cy_px], axis=1)


def project_with_jacobians(
    intr: Intrinsics, cam_from_part: np.ndarray, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project and differentiate.

    Returns:
        uv: (n, 2) pixels.
        J_point: (n, 2, 3) d(uv)/d(point in the part frame).
        J_pose: (n, 2, 6) d(uv)/d(xi) for the left perturbation
            ``cam_from_part' = Exp(xi) @ cam_from_part``, ``xi = (omega, tau)``.
    """
    T = np.asarray(cam_from_part, dtype=float)
    R = T[:3, :3]
    Xc = to_camera(T, points)
    x, y, z = Xc[:, 0], Xc[:, 1], Xc[:, 2]
    iz = 1.0 / z
    xy = np.stack([x * iz, y * iz], axis=1)
    # d(xy)/d(Xc): (n, 2, 3)
    dxy_dX = np.zeros((len(z), 2, 3))
    dxy_dX[:, 0, 0] = iz
    dxy_dX[:, 0, 2] = -x * iz * iz
    dxy_dX[:, 1, 1] = iz
    dxy_dX[:, 1, 2] = -y * iz * iz
    D = intr.distortion_jacobian(xy)
    F = np.diag([intr.fx_px, intr.fy_px])
    duv_dX = np.einsum("ij,njk,nkl->nil", F, D, dxy_dX)
    xyd = intr.distort(xy)
    uv = np.stack([intr.fx_px * xyd[:, 0] + intr.cx_px, intr.fy_px * xyd[:, 1] + intr.cy_px], axis=1)
    J_point = duv_dX @ R
    dX_dxi = np.concatenate([-skew(Xc), np.broadcast_to(np.eye(3), (len(z), 3, 3))], axis=2)
    J_pose = duv_dX @ dX_dxi
    return uv, J_point, J_pose


# --- projective <-> collinearity --------------------------------------------


def projection_matrix(intr: Intrinsics, cam_from_part: np.ndarray) -> np.ndarray:
    """``M = K [R | T]`` (seed eq. 1-2), (3, 4). Ignores distortion."""
    T = np.asarray(cam_from_part, dtype=float)
    return intr.K @ T[:3, :]


def decompose_projection_matrix(M: np.ndarray, width: int, height: int) -> tuple[Intrinsics, np.ndarray]:
    """Split a projection matrix into interior and exterior orientation.

    ``M`` is known up to scale; the scale and sign are fixed so that the camera
    has positive focal lengths and the points in front of it have ``z > 0`` when
    ``M``'s third row has the sign of a valid camera (``det(M[:, :3]) > 0`` after
    normalisation). Returns ``(intrinsics, cam_from_part)``; the skew of the
    upper-triangular factor is dropped (reported by the caller if significant).
    """
    M = np.asarray(M, dtype=float)
    A = M[:, :3]
    s = np.linalg.norm(A[2])
    if not np.isfinite(s) or s == 0:
        raise CalibrationError("projection matrix is degenerate (third row is zero)")
    M = M / s
    if np.linalg.det(M[:, :3]) < 0:
        M = -M
    # RQ decomposition A = K R
    K, R = _rq(M[:, :3])
    Dsign = np.diag(np.sign(np.diag(K)))
    K = K @ Dsign
    R = Dsign @ R
    t = np.linalg.solve(K, M[:, 3])
    if np.linalg.det(R) < 0:
        raise CalibrationError("projection matrix gives a left-handed camera frame")
    K = K / K[2, 2]
    intr = Intrinsics(fx_px=K[0, 0], fy_px=K[1, 1], cx_px=K[0, 2], cy_px=K[1, 2], width=width, height=height)
    return intr, make_pose(R, t)


def _rq(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    P = np.flipud(np.eye(3))
    Q, Rm = np.linalg.qr((P @ A).T)
    K = P @ Rm.T @ P
    R = P @ Q.T
    return K, R


def collinearity_from_pose(cam_from_part: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R, Pc)`` of the collinearity model ``X_cam = R (P - Pc)``, ``Pc = -R^T T`` (seed eq. 3-5)."""
    T = np.asarray(cam_from_part, dtype=float)
    R = T[:3, :3]
    return R.copy(), -R.T @ T[:3, 3]


def pose_from_collinearity(R: np.ndarray, Pc: np.ndarray) -> np.ndarray:
    """``cam_from_part`` from the collinearity parameters: ``T = -R Pc``, (4, 4)."""
    R = np.asarray(R, dtype=float)
    return make_pose(R, -R @ np.asarray(Pc, dtype=float))


def project_collinearity(intr: Intrinsics, R: np.ndarray, Pc: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Image points through the collinearity equations ``X_cam = R (P - Pc)``, (n, 2)."""
    Xc = (np.asarray(points, dtype=float) - Pc) @ np.asarray(R).T
    xy = intr.distort(Xc[:, :2] / Xc[:, 2:3])
    return np.stack([intr.fx_px * xy[:, 0] + intr.cx_px, intr.fy_px * xy[:, 1] + intr.cy_px], axis=1)
