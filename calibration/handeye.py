"""Hand-eye calibration of a robot-held camera: AX = XB, then a joint refinement on the images.

The unknowns are ``X = flange_from_cam`` (the hand-eye) and ``Y = base_from_target`` (where
the calibration artefact lies in the robot's base frame). Image ``i`` is taken with the
flange at ``B_i = base_from_flange`` (the robot's reading) and its exterior orientation
``A_i = cam_from_target`` comes from the measurement pipeline; for every image

    Y = B_i X A_i          (equivalently (B_j^-1 B_i) X = X (A_j A_i^-1): AX = XB)

Three steps (``calibrate_hand_eye``):

1. ``solve_opencv``: OpenCV's ``calibrateHandEye`` with each of its methods (Tsai-Lenz, Park,
   Horaud, Andreff, Daniilidis); ``Y`` follows from ``X`` as the chordal mean of ``B_i X A_i``.
   Each solution is scored by the consistency of ``B_i X A_i`` (rotation and translation
   spread about ``Y``).
2. ``refine_hand_eye``: a joint least-squares adjustment of ``X`` and ``Y`` (12 parameters) on
   the image observations themselves, ``uv_ij = project(K, X^-1 B_i^-1 Y, P_j)`` with the
   artefact's calibrated target coordinates ``P_j``, started from the best OpenCV solution
   (scipy ``least_squares``, Huber loss, then observations beyond ``reject_k`` sigma dropped
   and the adjustment repeated). This uses every observation with its proper weight instead
   of per-image poses whose errors are correlated and unequal.
3. Uncertainty: the covariance of the 12 parameters is ``s0^2 (J^T J)^-1`` at the solution
   (``s0`` the a-posteriori sigma of an image coordinate); the hand-eye block is rotated into
   the flange frame and reported as translation (m) and rotation (rad) standard deviations.

Parametrisation (all perturbations in the convention of :func:`calibration.camera.exp_se3`,
``xi = (omega, tau)``): ``X = X0 Exp(xi_X)`` (camera frame), ``Y = Exp(xi_Y) Y0`` (base
frame). With ``C_i = X0^-1 B_i^-1`` the pose of image ``i`` moves by the left perturbation
``-xi_X + Ad(C_i) xi_Y``, so the Jacobian is ``J_pose [-I, Ad(C_i)]``.

Station choice (``hand_eye_information``, ``select_stations``): the same linearisation
predicts the information ``J^T J / sigma^2`` that each candidate station adds; stations are
chosen greedily to maximise the determinant of the hand-eye block's Schur complement
(D-optimal for ``X`` with ``Y`` a nuisance), which favours large rotations about
non-parallel axes as Tsai and Lenz prescribe, but weighs them by what the images really see.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from calibration.camera import Intrinsics, exp_se3, invert, make_pose, project, project_with_jacobians, skew
from calibration.errors import CalibrationError

__all__ = [
    "METHODS",
    "HandEyeSolution",
    "HandEyeOptions",
    "HandEyeResult",
    "solve_opencv",
    "solve_ax_xb",
    "HAVE_CV2_HAND_EYE",
    "compare_methods",
    "mean_pose",
    "pose_consistency",
    "pose_error",
    "adjoint",
    "reprojection_jacobian",
    "refine_hand_eye",
    "hand_eye_information",
    "select_stations",
]

#: OpenCV's hand-eye methods, by the name used in reports.
METHODS: dict[str, int] = {
    "tsai": cv2.CALIB_HAND_EYE_TSAI,
    "park": cv2.CALIB_HAND_EYE_PARK,
    "horaud": cv2.CALIB_HAND_EYE_HORAUD,
    "andreff": cv2.CALIB_HAND_EYE_ANDREFF,
    "daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS,
}

#: The installed OpenCV binds ``calibrateHandEye`` (4.x does; the 5.0 Python wheel does not).
HAVE_CV2_HAND_EYE = hasattr(cv2, "calibrateHandEye")

# --- small SE(3) helpers ------------------------------------------------------------------


def adjoint(T: np.ndarray) -> np.ndarray:
    """Adjoint of ``T: (..., 4, 4)`` for ``xi = (omega, tau)``: ``T Exp(xi) T^-1 = Exp(Ad xi)``, (..., 6, 6)."""
    T = np.asarray(T, dtype=float)
    R, t = T[..., :3, :3], T[..., :3, 3]
    out = np.zeros(T.shape[:-2] + (6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., 3:, :3] = skew(t.reshape(-1, 3)).reshape(t.shape[:-1] + (3, 3)) @ R
    return out


def mean_pose(T: np.ndarray) -> np.ndarray:
    """Chordal mean of rigid transforms ``T: (n, 4, 4)`` (rotation projected back onto SO(3)), (4, 4)."""
    T = np.asarray(T, dtype=float)
    U, _, Vt = np.linalg.svd(T[:, :3, :3].sum(axis=0))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return make_pose(R, T[:, :3, 3].mean(axis=0))


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation angle (rad) of ``T_true^-1 T_est``."""
    D = invert(np.asarray(T_true, dtype=float)) @ np.asarray(T_est, dtype=float)
    return float(np.linalg.norm(D[:3, 3])), float(np.linalg.norm(Rotation.from_matrix(D[:3, :3]).as_rotvec()))


def pose_consistency(base_from_flange: np.ndarray, flange_from_cam: np.ndarray, cam_from_target: np.ndarray,
                     base_from_target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How far each image's ``B_i X A_i`` lies from ``Y``: translation (n,) m and rotation (n,) rad."""
    Yi = np.asarray(base_from_flange) @ np.asarray(flange_from_cam) @ np.asarray(cam_from_target)
    D = invert(np.asarray(base_from_target)) @ Yi
    rot = np.linalg.norm(Rotation.from_matrix(D[:, :3, :3]).as_rotvec(), axis=1)
    return np.linalg.norm(D[:, :3, 3], axis=1), rot


# --- step 1: closed-form AX = XB -------------------------------------------------------------
# NumPy versions of the methods behind cv2.calibrateHandEye, for OpenCV builds without the binding.
# Motions between every pair of stations (i, j): M = B_j^-1 B_i (flange), N = A_j A_i^-1 (camera),
# M X = X N. Rotation first (per method), then the common translation least squares
# (R_M - I) t_X = R_X t_N - t_M.


def _motion_pairs(B: np.ndarray, A: np.ndarray, min_angle_rad: float = np.deg2rad(2.0)) -> tuple[np.ndarray, np.ndarray]:
    i, j = np.triu_indices(len(B), 1)
    M = invert(B[j]) @ B[i]
    N = A[j] @ invert(A[i])
    ang = np.linalg.norm(Rotation.from_matrix(M[:, :3, :3]).as_rotvec(), axis=1)
    keep = ang > min_angle_rad
    if keep.sum() < 2:
        raise CalibrationError("hand-eye: fewer than two station pairs rotate by more than 2 degrees; "
                               "choose stations that rotate the camera about different axes")
    return M[keep], N[keep]


def _project_so3(R: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(R)
    return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt


def _rotation_tsai(M, N):
    """Tsai-Lenz: modified Rodrigues vectors, skew(P_M + P_N) P' = P_N - P_M."""
    def mrp(R):
        rv = Rotation.from_matrix(R).as_rotvec()
        th = np.linalg.norm(rv, axis=1, keepdims=True)
        return 2 * np.sin(th / 2) * rv / np.maximum(th, 1e-300)
    Pm, Pn = mrp(M[:, :3, :3]), mrp(N[:, :3, :3])
    lhs = skew(Pm + Pn).reshape(-1, 3)
    p1 = np.linalg.lstsq(lhs, (Pn - Pm).ravel(), rcond=None)[0]
    p = 2 * p1 / np.sqrt(1 + p1 @ p1)
    pp = p @ p
    return (1 - pp / 2) * np.eye(3) + 0.5 * (np.outer(p, p) + np.sqrt(4 - pp) * skew(p))


def _rotation_park(M, N):
    """Park-Martin: alpha_M = R_X alpha_N for the rotation vectors; orthogonal Procrustes."""
    a = Rotation.from_matrix(M[:, :3, :3]).as_rotvec()
    b = Rotation.from_matrix(N[:, :3, :3]).as_rotvec()
    return _project_so3(a.T @ b)


def _quat_wxyz(R):
    q = Rotation.from_matrix(R).as_quat()  # x, y, z, w
    q = np.concatenate([q[:, 3:], q[:, :3]], axis=1)
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def _qmat_left(q):
    w, x, y, z = q.T
    return np.stack([np.stack([w, -x, -y, -z], -1), np.stack([x, w, -z, y], -1),
                     np.stack([y, z, w, -x], -1), np.stack([z, -y, x, w], -1)], axis=1)


def _qmat_right(q):
    w, x, y, z = q.T
    return np.stack([np.stack([w, -x, -y, -z], -1), np.stack([x, w, z, -y], -1),
                     np.stack([y, -z, w, x], -1), np.stack([z, y, -x, w], -1)], axis=1)


def _rotation_horaud(M, N):
    """Horaud-Dornaika: unit quaternion minimising sum |q_M q_X - q_X q_N|^2 (smallest eigenvector)."""
    D = (_qmat_left(_quat_wxyz(M[:, :3, :3])) - _qmat_right(_quat_wxyz(N[:, :3, :3]))).reshape(-1, 4)
    q = np.linalg.svd(D)[2][-1]
    return Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()


def _rotation_andreff(M, N):
    """Andreff: vec(R_M R_X - R_X R_N) = (I x R_M - R_N^T x I) vec(R_X) = 0, null vector, back onto SO(3)."""
    I3 = np.eye(3)
    L = np.concatenate([np.kron(I3, m[:3, :3]) - np.kron(n[:3, :3].T, I3) for m, n in zip(M, N)])
    v = np.linalg.svd(L)[2][-1]
    R = v.reshape(3, 3, order="F")
    R = R * np.sign(np.linalg.det(R)) / abs(np.linalg.det(R)) ** (1 / 3)
    return _project_so3(R)


def _dq(T):
    """Dual quaternions (w, x, y, z) of transforms ``T: (k, 4, 4)``: real (k, 4), dual (k, 4)."""
    r = _quat_wxyz(T[:, :3, :3])
    t = np.concatenate([np.zeros((len(T), 1)), T[:, :3, 3]], axis=1)
    d = 0.5 * np.einsum("kij,kj->ki", _qmat_left(t), r)
    return r, d


def _solve_daniilidis(M, N):
    """Daniilidis: dual quaternions, the 2-dimensional null space of the stacked 6 x 8 system."""
    am, bm = _dq(M)
    an, bn = _dq(N)
    rows = []
    for a, b, a2, b2 in zip(am, bm, an, bn):
        # screw axes: vector parts; a - a2 and b - b2 must be orthogonal-compatible: 6 equations
        va, vb, va2, vb2 = a[1:], b[1:], a2[1:], b2[1:]
        top = np.hstack([(va - va2)[:, None], skew(va + va2), np.zeros((3, 4))])
        bot = np.hstack([(vb - vb2)[:, None], skew(vb + vb2), (va - va2)[:, None], skew(va + va2)])
        rows.append(np.vstack([top, bot]))
    T = np.vstack(rows)
    V = np.linalg.svd(T)[2]
    v7, v8 = V[-2], V[-1]
    u1, v1, u2, v2 = v7[:4], v7[4:], v8[:4], v8[4:]
    a_, b_, c_ = u1 @ v1, u1 @ v2 + u2 @ v1, u2 @ v2
    s_roots = np.roots([a_, b_, c_]) if abs(a_) > 1e-15 else np.array([-c_ / b_])
    s_roots = np.real(s_roots[np.isreal(s_roots)])
    if len(s_roots) == 0:
        raise CalibrationError("hand-eye (Daniilidis): no real solution; the motions are degenerate")
    best = None
    for s in s_roots:
        val = s * s * (u1 @ u1) + 2 * s * (u1 @ u2) + u2 @ u2
        if best is None or val > best[0]:
            best = (val, s)
    val, s = best
    lam2 = np.sqrt(1.0 / val)
    lam1 = s * lam2
    q = lam1 * v7 + lam2 * v8
    r, d = q[:4], q[4:]
    Rx = Rotation.from_quat([r[1], r[2], r[3], r[0]]).as_matrix()
    rc = r * np.array([1.0, -1.0, -1.0, -1.0])
    t = 2 * (_qmat_left(d[None])[0] @ rc)[1:]
    return make_pose(Rx, t)


def _translation(M, N, Rx):
    lhs = (M[:, :3, :3] - np.eye(3)).reshape(-1, 3)
    rhs = (np.einsum("ij,kj->ki", Rx, N[:, :3, 3]) - M[:, :3, 3]).ravel()
    return np.linalg.lstsq(lhs, rhs, rcond=None)[0]


_ROTATION = {"tsai": _rotation_tsai, "park": _rotation_park, "horaud": _rotation_horaud, "andreff": _rotation_andreff}


def solve_ax_xb(base_from_flange: np.ndarray, cam_from_target: np.ndarray, method: str) -> np.ndarray:
    """``flange_from_cam`` (4, 4) by one published method over all pairs of stations (NumPy)."""
    B, A = _check_pairs(base_from_flange, cam_from_target)
    M, N = _motion_pairs(B, A)
    if method == "daniilidis":
        return _solve_daniilidis(M, N)
    if method not in _ROTATION:
        raise CalibrationError(f"unknown hand-eye method {method!r}; use one of {', '.join(METHODS)}")
    Rx = _rotation_tsai(M, N) if method == "tsai" else _ROTATION[method](M, N)
    return make_pose(Rx, _translation(M, N, Rx))


# --- step 1: OpenCV ---------------------------------------------------------------------------


@dataclass(frozen=True)
class HandEyeSolution:
    """One closed-form solution.

    Attributes:
        method: OpenCV method name (:data:`METHODS`).
        flange_from_cam: (4, 4) X.
        base_from_target: (4, 4) Y, the chordal mean of ``B_i X A_i``.
        rms_translation_m, rms_rotation_rad: spread of ``B_i X A_i`` about Y (consistency).
    """

    method: str
    flange_from_cam: np.ndarray
    base_from_target: np.ndarray
    rms_translation_m: float
    rms_rotation_rad: float
    backend: str = "opencv"


def _check_pairs(base_from_flange: np.ndarray, cam_from_target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    B = np.asarray(base_from_flange, dtype=float)
    A = np.asarray(cam_from_target, dtype=float)
    if B.ndim != 3 or B.shape[1:] != (4, 4) or A.shape != B.shape:
        raise CalibrationError(f"hand-eye needs (n, 4, 4) robot and camera poses of the same n; got {B.shape}, {A.shape}")
    if len(B) < 3:
        raise CalibrationError(f"hand-eye needs at least 3 stations (rotations about two axes), got {len(B)}")
    return B, A


def solve_opencv(base_from_flange: np.ndarray, cam_from_target: np.ndarray, method: str = "tsai",
                 backend: str = "auto") -> HandEyeSolution:
    """One closed-form AX = XB solution; ``base_from_flange, cam_from_target: (n, 4, 4)``.

    ``backend``: "opencv" (``cv2.calibrateHandEye``), "numpy" (:func:`solve_ax_xb`, the same published
    methods over all station pairs), or "auto" (OpenCV when it is bound, else NumPy).
    """
    B, A = _check_pairs(base_from_flange, cam_from_target)
    if method not in METHODS:
        raise CalibrationError(f"unknown hand-eye method {method!r}; use one of {', '.join(METHODS)}")
    use_cv = backend == "opencv" or (backend == "auto" and HAVE_CV2_HAND_EYE)
    if use_cv:
        if not HAVE_CV2_HAND_EYE:
            raise CalibrationError(f"OpenCV {cv2.__version__} has no calibrateHandEye binding; use backend='numpy'")
        R, t = cv2.calibrateHandEye(list(B[:, :3, :3]), list(B[:, :3, 3].reshape(-1, 3, 1)),
                                    list(A[:, :3, :3]), list(A[:, :3, 3].reshape(-1, 3, 1)), method=METHODS[method])
        X = make_pose(np.asarray(R, dtype=float), np.asarray(t, dtype=float).ravel())
    else:
        X = solve_ax_xb(B, A, method)
    if not np.all(np.isfinite(X)):
        raise CalibrationError(f"hand-eye method {method}: no solution (degenerate motions: rotate about more axes)")
    Y = mean_pose(B @ X @ A)
    dt, dr = pose_consistency(B, X, A, Y)
    return HandEyeSolution(method, X, Y, float(np.sqrt(np.mean(dt**2))), float(np.sqrt(np.mean(dr**2))),
                           "opencv" if use_cv else "numpy")


def compare_methods(base_from_flange: np.ndarray, cam_from_target: np.ndarray,
                    methods: tuple[str, ...] = tuple(METHODS), backend: str = "auto") -> list[HandEyeSolution]:
    """Every method's solution, best (smallest translation spread) first; failures are skipped."""
    out = []
    for m in methods:
        try:
            out.append(solve_opencv(base_from_flange, cam_from_target, m, backend))
        except (CalibrationError, cv2.error):
            continue
    if not out:
        raise CalibrationError("hand-eye: every OpenCV method failed; the stations' rotations are degenerate")
    return sorted(out, key=lambda s: (s.rms_translation_m, s.rms_rotation_rad))


# --- step 2: joint refinement on the images ------------------------------------------------------


def reprojection_jacobian(intr: Intrinsics, base_from_flange: np.ndarray, flange_from_cam: np.ndarray,
                          base_from_target: np.ndarray, obs_image: np.ndarray, obs_xyz: np.ndarray,
                          jacobian: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Predicted pixels and their Jacobian with respect to ``(xi_X, xi_Y)``.

    Args:
        base_from_flange: (m, 4, 4) robot poses; obs_image: (q,) image of each observation;
        obs_xyz: (q, 3) target coordinates (artefact frame).
    Returns:
        uv: (q, 2); J: (q, 2, 12) (columns: xi_X (6), xi_Y (6)), None without ``jacobian``.
    """
    B = np.asarray(base_from_flange, dtype=float)
    C = invert(np.asarray(flange_from_cam, dtype=float)) @ invert(B)  # cam_from_base per image
    T = C @ np.asarray(base_from_target, dtype=float)  # cam_from_target per image
    q = len(obs_image)
    uv = np.zeros((q, 2))
    if not jacobian:
        for i in np.unique(obs_image):
            sel = obs_image == i
            uv[sel] = project(intr, T[i], obs_xyz[sel])
        return uv, None
    AdC = adjoint(C)
    J = np.zeros((q, 2, 12))
    for i in np.unique(obs_image):
        sel = obs_image == i
        u, _, Jp = project_with_jacobians(intr, T[i], obs_xyz[sel])
        uv[sel] = u
        J[sel, :, :6] = -Jp
        J[sel, :, 6:] = Jp @ AdC[i]
    return uv, J


@dataclass(frozen=True)
class HandEyeOptions:
    """How the joint refinement solves.

    Attributes:
        sigma_px: a-priori sigma of an image coordinate (Huber threshold is 3 of them).
        reject_k: observations whose residual exceeds ``reject_k * s0`` are dropped, then re-solved.
        max_rounds: rejection rounds.
        fix_flange_from_cam: hold X (estimate only Y: the part placement).
    """

    sigma_px: float = 0.05
    reject_k: float = 4.0
    max_rounds: int = 3
    fix_flange_from_cam: bool = False


@dataclass
class HandEyeResult:
    """The refined hand-eye and artefact placement.

    Attributes:
        flange_from_cam: (4, 4) X.
        base_from_target: (4, 4) Y.
        cov: (12, 12) covariance of ``(xi_X, xi_Y)`` (rad^2, m^2), in the solution's tangent space.
        sigma_translation_m: (3,) std of X's translation, flange frame.
        sigma_rotation_rad: (3,) std of X's rotation about the flange axes.
        sigma0_px: a-posteriori sigma of an image coordinate.
        residuals: (q, 2) observed minus computed pixels (rejected ones too).
        rejected: (q,) observations left out.
        dof: redundancy.
        per_image_rms_px: (m,) rms residual of each image.
    """

    flange_from_cam: np.ndarray
    base_from_target: np.ndarray
    cov: np.ndarray
    sigma_translation_m: np.ndarray
    sigma_rotation_rad: np.ndarray
    sigma0_px: float
    residuals: np.ndarray
    rejected: np.ndarray
    dof: int
    per_image_rms_px: np.ndarray
    history: list = field(default_factory=list)

    def summary(self) -> dict:
        return {"sigma0_px": self.sigma0_px, "dof": self.dof, "n_rejected": int(self.rejected.sum()),
                "sigma_translation_m": self.sigma_translation_m, "sigma_rotation_rad": self.sigma_rotation_rad}


def _compose(X0, Y0, p, fix_x):
    X = X0 if fix_x else X0 @ exp_se3(p[:6])
    Y = exp_se3(p[-6:]) @ Y0
    return X, Y


def refine_hand_eye(intr: Intrinsics, base_from_flange: np.ndarray, obs_image: np.ndarray, obs_xyz: np.ndarray,
                    obs_uv: np.ndarray, flange_from_cam0: np.ndarray, base_from_target0: np.ndarray,
                    options: HandEyeOptions | None = None) -> HandEyeResult:
    """Joint least-squares refinement of X and Y on the image observations.

    Args:
        intr: the camera's interior orientation (held fixed).
        base_from_flange: (m, 4, 4) robot poses at the images.
        obs_image: (q,) int image index; obs_xyz: (q, 3) artefact target coordinates; obs_uv: (q, 2) pixels.
        flange_from_cam0, base_from_target0: (4, 4) starting values (e.g. the best OpenCV solution).
    """
    o = options or HandEyeOptions()
    obs_image = np.asarray(obs_image, dtype=int)
    obs_xyz = np.asarray(obs_xyz, dtype=float).reshape(-1, 3)
    obs_uv = np.asarray(obs_uv, dtype=float).reshape(-1, 2)
    B = np.asarray(base_from_flange, dtype=float)
    n_par = 6 if o.fix_flange_from_cam else 12
    if len(obs_uv) * 2 <= n_par + 6:
        raise CalibrationError(f"hand-eye refinement: {len(obs_uv)} observations are too few for {n_par} unknowns")
    X, Y = np.asarray(flange_from_cam0, dtype=float), np.asarray(base_from_target0, dtype=float)
    active = np.ones(len(obs_uv), dtype=bool)
    history = []
    for _round in range(o.max_rounds + 1):
        idx = np.flatnonzero(active)

        def fun(p, X=X, Y=Y, idx=idx):
            Xp, Yp = _compose(X, Y, p, o.fix_flange_from_cam)
            uv, _ = reprojection_jacobian(intr, B, Xp, Yp, obs_image[idx], obs_xyz[idx], jacobian=False)
            return (uv - obs_uv[idx]).ravel() / o.sigma_px

        def jac(p, X=X, Y=Y, idx=idx):
            # the tangent-space Jacobian at the composed point: exact at p = 0, first order beyond
            Xp, Yp = _compose(X, Y, p, o.fix_flange_from_cam)
            _, J = reprojection_jacobian(intr, B, Xp, Yp, obs_image[idx], obs_xyz[idx])
            J = J.reshape(-1, 12) / o.sigma_px
            return J[:, 6:] if o.fix_flange_from_cam else J

        sol = least_squares(fun, np.zeros(n_par), jac=jac, method="trf", loss="huber", f_scale=3.0,
                            xtol=1e-10, ftol=1e-10, gtol=1e-10, max_nfev=100)
        X, Y = _compose(X, Y, sol.x, o.fix_flange_from_cam)
        uv, _ = reprojection_jacobian(intr, B, X, Y, obs_image, obs_xyz, jacobian=False)
        res = obs_uv - uv
        dof = 2 * len(idx) - n_par
        s0 = float(np.sqrt(np.sum(res[active] ** 2) / max(dof, 1)))
        history.append({"round": _round, "n_obs": int(len(idx)), "sigma0_px": s0, "nfev": int(sol.nfev)})
        bad = np.linalg.norm(res, axis=1) > o.reject_k * s0 * np.sqrt(2.0)
        new = active & ~bad
        if np.array_equal(new, active) or new.sum() * 2 <= n_par + 6:
            break
        active = new
    uv, J = reprojection_jacobian(intr, B, X, Y, obs_image, obs_xyz)
    Ja = J[active].reshape(-1, 12)
    if o.fix_flange_from_cam:
        Ja = Ja[:, 6:]
    N = Ja.T @ Ja
    try:
        Q = np.linalg.inv(N)
    except np.linalg.LinAlgError:
        raise CalibrationError("hand-eye refinement: singular normal equations; the stations do not determine "
                               "the hand-eye (rotate about at least two non-parallel axes)") from None
    cov = np.zeros((12, 12))
    if o.fix_flange_from_cam:
        cov[6:, 6:] = s0**2 * Q
    else:
        cov = s0**2 * Q
    R = X[:3, :3]
    c_rot = R @ cov[:3, :3] @ R.T
    c_tr = R @ cov[3:6, 3:6] @ R.T
    per_image = np.array([np.sqrt(np.mean(np.sum(res[active & (obs_image == i)] ** 2, axis=1)))
                          if np.any(active & (obs_image == i)) else np.nan for i in range(len(B))])
    return HandEyeResult(
        flange_from_cam=X, base_from_target=Y, cov=cov,
        sigma_translation_m=np.sqrt(np.clip(np.diag(c_tr), 0, None)),
        sigma_rotation_rad=np.sqrt(np.clip(np.diag(c_rot), 0, None)),
        sigma0_px=s0, residuals=res, rejected=~active, dof=int(2 * active.sum() - n_par),
        per_image_rms_px=per_image, history=history,
    )


# --- station choice ----------------------------------------------------------------------------


def hand_eye_information(intr: Intrinsics, part_from_cam: np.ndarray, visible: np.ndarray, xyz: np.ndarray,
                         flange_from_cam: np.ndarray, base_from_target: np.ndarray, sigma_px: float) -> np.ndarray:
    """Information ``J^T J / sigma^2`` (m, 12, 12) that each candidate station adds about ``(xi_X, xi_Y)``.

    Args:
        part_from_cam: (m, 4, 4) candidate stations (artefact frame); visible: (m, n) which targets each measures;
        xyz: (n, 3) targets; flange_from_cam, base_from_target: (4, 4) nominal values.
    """
    P = np.asarray(part_from_cam, dtype=float)
    X = np.asarray(flange_from_cam, dtype=float)
    Y = np.asarray(base_from_target, dtype=float)
    B = Y @ P @ invert(X)
    out = np.zeros((len(P), 12, 12))
    for i in range(len(P)):
        sel = np.flatnonzero(visible[i])
        if len(sel) == 0:
            continue
        _, J = reprojection_jacobian(intr, B[i:i + 1], X, Y, np.zeros(len(sel), dtype=int), xyz[sel])
        Jf = J.reshape(-1, 12)
        out[i] = Jf.T @ Jf / sigma_px**2
    return out


def select_stations(info: np.ndarray, k: int, eligible: np.ndarray | None = None,
                    prior: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Greedy D-optimal choice of ``k`` stations from ``info: (m, 12, 12)``.

    Each step adds the station that most increases ``log det`` of the hand-eye block's Schur
    complement. ``prior`` (a tiny diagonal information) makes the first, rank-deficient steps
    well defined. Returns the chosen indices (in the order chosen) and the criterion after each.
    """
    info = np.asarray(info, dtype=float)
    m = len(info)
    ok = np.ones(m, dtype=bool) if eligible is None else np.asarray(eligible, dtype=bool).copy()
    if ok.sum() < k:
        raise CalibrationError(f"hand-eye planning: {int(ok.sum())} usable stations, {k} needed")
    N = prior * np.eye(12)
    chosen, crit = [], []
    for _ in range(k):
        cand = np.flatnonzero(ok)
        # batched Schur complements of N + info[c]
        M = N[None] + info[cand]
        S = M[:, :6, :6] - M[:, :6, 6:] @ np.linalg.solve(M[:, 6:, 6:], M[:, 6:, :6])
        sign, ld = np.linalg.slogdet(0.5 * (S + np.swapaxes(S, 1, 2)))
        ld = np.where(sign > 0, ld, -np.inf)
        j = int(cand[int(np.argmax(ld))])
        chosen.append(j)
        crit.append(float(np.max(ld)))
        N = N + info[j]
        ok[j] = False
    return np.array(chosen, dtype=int), np.array(crit)
