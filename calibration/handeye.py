"""Hand-eye calibration of a robot-held camera: AX = XB, then a joint refinement on the images.

The unknowns are ``X = flange_from_cam`` (the hand-eye) and ``Y = base_from_target`` (where
the calibration artefact lies in the robot's base frame). Image ``i`` is taken with the
flange at ``B_i = base_from_flange`` (the robot's reading) and its exterior orientation
``A_i = cam_from_target`` comes from the measurement pipeline; for every image

    Y = B_i X A_i          (equivalently (B_j^-1 B_i) X = X (A_j A_i^-1): AX = XB)

Three steps (``cell.cellcal.handeye.run_hand_eye``):

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

Conditioning of a set of stations (``hand_eye_information``, ``hand_eye_conditioning``): the
same linearisation predicts the information ``J^T J / sigma^2`` that each station adds; its sum,
reduced to ``X`` by the Schur complement (``Y`` a nuisance), predicts X's precision before any
image is taken. With it, :func:`weakest_rotation` measures what the closed-form methods need:
rotations about non-parallel axes (Tsai and Lenz). The stations themselves come from the
network planner (``cell.cellcal.common.plan_stations``); these figures check them.
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
    "MIN_WEAKEST_ROTATION_RAD",
    "weakest_rotation",
    "compare_methods",
    "mean_pose",
    "pose_consistency",
    "pose_error",
    "adjoint",
    "reprojection_jacobian",
    "refine_hand_eye",
    "hand_eye_information",
    "HandEyeConditioning",
    "hand_eye_conditioning",
]

#: OpenCV's hand-eye methods, by the name used in reports.
METHODS: dict[str, int] = {
    "tsai": cv2.CALIB_HAND_EYE_TSAI,
    "park": cv2.CALIB_HAND_EYE_PARK,
    "horaud": cv2.CALIB_HAND_EYE_HORAUD,
    "andreff": cv2.CALIB_HAND_EYE_ANDREFF,
    "daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS,
}

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


# --- conditioning of AX = XB -------------------------------------------------------------------


def weakest_rotation(poses: np.ndarray) -> tuple[float, np.ndarray]:
    """How well the relative motions of ``poses: (m, 4, 4)`` determine a hand-eye: ``(angle (rad), axis (3,))``.

    For every pair of stations the relative rotation ``R = R_j^T R_i`` (flange motions for
    ``base_from_flange``, camera motions for ``part_from_cam``: the same angles, axes turned by the
    hand-eye). The closed-form methods solve the translation of X from the stacked
    ``(R - I) t_X = ...``, and ``(R - I)^T (R - I) = 2 (1 - cos theta) (I - a a^T)`` for a rotation by
    ``theta`` about ``a``: along a direction ``u`` the motions inform ``t_X`` by the mean of
    ``2 (1 - cos theta) sin^2(a, u)``. Its smallest eigenvalue ``lambda`` (eigenvector ``axis``, in
    the frame of the second pose of each pair) is returned as the equivalent angle
    ``arccos(1 - lambda / 2)``: the rotation which, made about an axis perpendicular to ``axis`` by
    every motion, would inform it as much. 0 for pure translations or rotations about one axis
    only (the hand-eye is then undetermined, Tsai and Lenz), 180 degrees at best.
    """
    T = np.asarray(poses, dtype=float)
    if len(T) < 2:
        return 0.0, np.array([0.0, 0.0, 1.0])
    i, j = np.triu_indices(len(T), 1)
    D = np.swapaxes(T[j, :3, :3], 1, 2) @ T[i, :3, :3] - np.eye(3)
    G = np.einsum("kji,kjl->il", D, D) / len(D)
    w, V = np.linalg.eigh(G)
    return float(np.arccos(np.clip(1.0 - w[0] / 2.0, -1.0, 1.0))), V[:, 0]


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


#: Closed-form methods need the flange to rotate about two axes at least; below this
#: :func:`weakest_rotation` the motions are called degenerate.
MIN_WEAKEST_ROTATION_RAD = float(np.deg2rad(2.0))


def _check_pairs(base_from_flange: np.ndarray, cam_from_target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    B = np.asarray(base_from_flange, dtype=float)
    A = np.asarray(cam_from_target, dtype=float)
    if B.ndim != 3 or B.shape[1:] != (4, 4) or A.shape != B.shape:
        raise CalibrationError(f"hand-eye needs (n, 4, 4) robot and camera poses of the same n; got {B.shape}, {A.shape}")
    if len(B) < 3:
        raise CalibrationError(f"hand-eye needs at least 3 stations (rotations about two axes), got {len(B)}")
    weak, axis = weakest_rotation(B)
    if weak < MIN_WEAKEST_ROTATION_RAD:
        raise CalibrationError(
            f"hand-eye: the flange motions leave the direction {np.round(axis, 2).tolist()} (flange frame) "
            f"undetermined (weakest rotation {np.rad2deg(weak):.2f} deg < {np.rad2deg(MIN_WEAKEST_ROTATION_RAD):.0f}); "
            "choose stations that rotate the camera about different axes")
    return B, A


def solve_opencv(base_from_flange: np.ndarray, cam_from_target: np.ndarray, method: str = "tsai") -> HandEyeSolution:
    """One closed-form AX = XB solution by ``cv2.calibrateHandEye``; ``base_from_flange, cam_from_target: (n, 4, 4)``.

    OpenCV's convention: ``R_gripper2base, t_gripper2base`` is ``base_from_flange``,
    ``R_target2cam, t_target2cam`` is ``cam_from_target``, the answer ``R_cam2gripper`` is ``flange_from_cam``.
    """
    B, A = _check_pairs(base_from_flange, cam_from_target)
    if method not in METHODS:
        raise CalibrationError(f"unknown hand-eye method {method!r}; use one of {', '.join(METHODS)}")
    # translations in millimetres: Andreff's method solves rotation and translation in one linear system
    # whose rotation rows are unitless; in metres they outweigh the translation rows that fix the scale of
    # vec(R), which then shrinks towards singular ("determinant(R) is null"). The other methods do not care.
    k = 1000.0
    R, t = cv2.calibrateHandEye(list(B[:, :3, :3]), list(k * B[:, :3, 3].reshape(-1, 3, 1)),
                                list(A[:, :3, :3]), list(k * A[:, :3, 3].reshape(-1, 3, 1)), method=METHODS[method])
    X = make_pose(np.asarray(R, dtype=float), np.asarray(t, dtype=float).ravel() / k)
    if not np.all(np.isfinite(X)):
        raise CalibrationError(f"hand-eye method {method}: no solution (degenerate motions: rotate about more axes)")
    if abs(np.linalg.det(X[:3, :3]) - 1.0) > 1e-6:
        raise CalibrationError(f"hand-eye method {method}: not a rotation (det {np.linalg.det(X[:3, :3]):.6f})")
    Y = mean_pose(B @ X @ A)
    dt, dr = pose_consistency(B, X, A, Y)
    return HandEyeSolution(method, X, Y, float(np.sqrt(np.mean(dt**2))), float(np.sqrt(np.mean(dr**2))))


def compare_methods(base_from_flange: np.ndarray, cam_from_target: np.ndarray,
                    methods: tuple[str, ...] = tuple(METHODS)) -> tuple[list[HandEyeSolution], dict[str, str]]:
    """Every method's solution, best (smallest translation spread) first, and ``{method: why}`` of those that failed."""
    _check_pairs(base_from_flange, cam_from_target)
    out, failed = [], {}
    for m in methods:
        try:
            out.append(solve_opencv(base_from_flange, cam_from_target, m))
        except (CalibrationError, cv2.error) as exc:
            failed[m] = str(exc).strip().splitlines()[-1]
    if not out:
        raise CalibrationError("hand-eye: every OpenCV method failed (" + "; ".join(f"{k}: {v}" for k, v in failed.items())
                               + "); the stations' rotations are degenerate")
    return sorted(out, key=lambda s: (s.rms_translation_m, s.rms_rotation_rad)), failed


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


#: the lens terms :func:`refine_with_lens` can estimate, and the step (in their units) its numerical Jacobian takes:
#: the principal distance (relative; fx and fy together), the principal point (px), the distortion terms
LENS_TERMS = {"f": 1e-6, "cx": 1e-2, "cy": 1e-2, "k1": 1e-5, "k2": 1e-5, "k3": 1e-5, "p1": 1e-7, "p2": 1e-7}


def lens_moved(start: Intrinsics, terms: tuple[str, ...], q: np.ndarray) -> Intrinsics:
    """``start`` moved by ``q`` (one value per name in ``terms``: ``f`` relative, the others added)."""
    from dataclasses import replace

    ch = {}
    for name, v in zip(terms, q):
        if name == "f":
            ch["fx_px"], ch["fy_px"] = start.fx_px * (1.0 + v), start.fy_px * (1.0 + v)
        else:
            key = {"cx": "cx_px", "cy": "cy_px"}.get(name, name)
            ch[key] = getattr(start, key) + v
    return replace(start, **ch)


@dataclass
class LensRefinement:
    """X, Y and the lens adjusted together (:func:`refine_with_lens`).

    Attributes:
        flange_from_cam, base_from_target: (4, 4) X and Y; lens: the interior orientation found.
        cov: (12 + L, 12 + L) covariance of ``(xi_X, xi_Y, lens terms)`` (``s0^2 (J^T J)^-1``; X's rows and columns
            zero when X was held); gain: (12 + L, 2q) ``(J^T J)^-1 J^T`` (for bounds of a bias common to the dots).
        terms: the lens terms' names; sigma0_px; dof; converged: the solver met its tolerances (the caller says
            and refuses what did not).
    """

    flange_from_cam: np.ndarray
    base_from_target: np.ndarray
    lens: Intrinsics
    cov: np.ndarray
    gain: np.ndarray
    terms: tuple
    sigma0_px: float
    dof: int
    converged: bool = True

    def lens_sigma(self) -> dict:
        """Each lens term's sigma (``f`` relative, ``cx, cy`` px, the distortion terms as they are)."""
        return {t: float(np.sqrt(max(self.cov[12 + k, 12 + k], 0.0))) for k, t in enumerate(self.terms)}


def refine_with_lens(start: Intrinsics, base_from_flange: np.ndarray, obs_image: np.ndarray, obs_xyz: np.ndarray,
                     obs_uv: np.ndarray, flange_from_cam0: np.ndarray, base_from_target0: np.ndarray,
                     terms: tuple[str, ...] = ("f", "cx", "cy", "k1", "k2"), fix_flange_from_cam: bool = False
                     ) -> LensRefinement:
    """X, Y and the lens's ``terms`` (:data:`LENS_TERMS`) adjusted together on observations already screened (e.g.
    by :func:`refine_hand_eye`, whose solution is a good start), least squares.

    A lens is not its data sheet: held at it, its principal distance scales every depth and its distortion moves
    the outer dots, and X and Y absorb both (decision 0055). The robot's known motion between the images fixes the
    scale, so the lens is determined with them; its uncertainty enters theirs through the joint covariance.
    """
    obs_image = np.asarray(obs_image, dtype=int)
    obs_xyz = np.asarray(obs_xyz, dtype=float).reshape(-1, 3)
    obs_uv = np.asarray(obs_uv, dtype=float).reshape(-1, 2)
    B = np.asarray(base_from_flange, dtype=float)
    X0, Y0 = np.asarray(flange_from_cam0, dtype=float), np.asarray(base_from_target0, dtype=float)
    terms = tuple(terms)
    n_pose = 6 if fix_flange_from_cam else 12
    n = n_pose + len(terms)
    if 2 * len(obs_uv) <= n + 6:
        raise CalibrationError(f"lens refinement: {len(obs_uv)} observations are too few for {n} unknowns")
    steps = np.r_[np.full(n_pose, 1e-7), [LENS_TERMS[t] for t in terms]]

    def split(p):
        X, Y = _compose(X0, Y0, np.r_[np.zeros(6), p[:6]] if fix_flange_from_cam else p[:12], fix_flange_from_cam)
        return X, Y, lens_moved(start, terms, p[n_pose:])

    def resid(p):
        X, Y, lens = split(p)
        uv, _ = reprojection_jacobian(lens, B, X, Y, obs_image, obs_xyz, jacobian=False)
        return (uv - obs_uv).ravel()

    def jac(p):
        X, Y, lens = split(p)
        _, Jp = reprojection_jacobian(lens, B, X, Y, obs_image, obs_xyz)
        Jp = Jp.reshape(-1, 12)[:, 6:] if fix_flange_from_cam else Jp.reshape(-1, 12)
        Jl = np.empty((2 * len(obs_uv), len(terms)))
        for k in range(len(terms)):
            h = np.zeros(n)
            h[n_pose + k] = steps[n_pose + k]
            Jl[:, k] = (resid(p + h) - resid(p - h)) / (2 * steps[n_pose + k])
        return np.hstack([Jp, Jl])

    sol = least_squares(resid, np.zeros(n), jac=jac, method="trf", x_scale="jac", xtol=1e-12, ftol=1e-12,
                        gtol=1e-12, max_nfev=50)
    X, Y, lens = split(sol.x)
    # covariance at the solution (the tangent there is the start's to first order: the steps are small)
    J = jac(np.r_[sol.x])
    r = resid(sol.x)
    dof = int(len(r) - n)
    s0 = float(np.sqrt(r @ r / max(dof, 1)))
    d = np.sqrt(np.maximum(np.einsum("ij,ij->j", J, J), 1e-300))  # column scaling: a metre and a pixel differ
    Js = J / d
    try:
        Qs = np.linalg.inv(Js.T @ Js)
    except np.linalg.LinAlgError:
        raise CalibrationError("lens refinement: singular normal equations; these stations cannot tell the lens from "
                               "the poses (more stations, other distances and tilts)") from None
    Q = Qs / np.outer(d, d)
    G = Q @ J.T
    cov = np.zeros((12 + len(terms), 12 + len(terms)))
    gain = np.zeros((12 + len(terms), len(r)))
    idx = np.r_[np.arange(6, 12), np.arange(12, 12 + len(terms))] if fix_flange_from_cam else np.arange(n)
    cov[np.ix_(idx, idx)] = s0**2 * Q
    gain[idx] = G
    return LensRefinement(X, Y, lens, cov, gain, terms, s0, dof, bool(sol.success))


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


@dataclass(frozen=True)
class HandEyeConditioning:
    """How well a set of stations determines the hand-eye, before any image is taken.

    Attributes:
        sigma_translation_m: (3,) predicted std of X's translation (flange axes), Y eliminated.
        sigma_rotation_rad: (3,) predicted std of X's rotation about the flange axes.
        weakest_rotation_rad: :func:`weakest_rotation` of the stations' motions.
        weakest_axis: (3,) its direction (camera frame).
        pivot_rms_m: how far the flange motions are from all turning about one fixed point (rms of
            ``(I - R_ij) c - t_ij`` at the best ``c``): near 0 when every station looks at one point from one
            distance, where Andreff's joint linear system has the false solution ``R = 0, t = c``.
        n_stations: stations counted.
    """

    sigma_translation_m: np.ndarray
    sigma_rotation_rad: np.ndarray
    weakest_rotation_rad: float
    weakest_axis: np.ndarray
    pivot_rms_m: float
    n_stations: int

    def shortfall(self, max_sigma_translation_m: float, max_sigma_rotation_rad: float,
                  min_weakest_rotation_rad: float) -> list[str]:
        """What misses the requirement (empty: met); sigmas compared by their norms."""
        st, sr = float(np.linalg.norm(self.sigma_translation_m)), float(np.linalg.norm(self.sigma_rotation_rad))
        out = []
        if not st <= max_sigma_translation_m:
            out.append(f"predicted sigma of the translation {st * 1e3:.4f} mm > {max_sigma_translation_m * 1e3:.4f} mm")
        if not sr <= max_sigma_rotation_rad:
            out.append(f"predicted sigma of the rotation {np.rad2deg(sr):.5f} deg > {np.rad2deg(max_sigma_rotation_rad):.5f} deg")
        if not self.weakest_rotation_rad >= min_weakest_rotation_rad:
            out.append(f"weakest rotation {np.rad2deg(self.weakest_rotation_rad):.1f} deg < "
                       f"{np.rad2deg(min_weakest_rotation_rad):.1f} deg")
        return out

    def to_dict(self) -> dict:
        return {"sigma_translation_m": self.sigma_translation_m.tolist(),
                "sigma_rotation_rad": self.sigma_rotation_rad.tolist(),
                "weakest_rotation_rad": self.weakest_rotation_rad, "weakest_axis": self.weakest_axis.tolist(),
                "pivot_rms_m": self.pivot_rms_m, "n_stations": self.n_stations}


def hand_eye_conditioning(info: np.ndarray, part_from_cam: np.ndarray, flange_from_cam: np.ndarray) -> HandEyeConditioning:
    """Predicted precision of X from ``info: (m, 12, 12)`` (:func:`hand_eye_information`) and the motions' spread.

    The normal matrix ``N = sum info`` is reduced to X by the Schur complement (Y is a nuisance);
    its inverse is X's covariance in the camera frame, turned into the flange frame as
    :func:`refine_hand_eye` reports it. ``part_from_cam: (m, 4, 4)`` gives :func:`weakest_rotation`.
    """
    N = np.asarray(info, dtype=float).sum(axis=0)
    S = N[:6, :6] - N[:6, 6:] @ np.linalg.solve(N[6:, 6:] + 1e-12 * np.eye(6), N[6:, :6])
    try:
        C = np.linalg.inv(0.5 * (S + S.T))
    except np.linalg.LinAlgError:
        C = np.full((6, 6), np.inf)
    R = np.asarray(flange_from_cam, dtype=float)[:3, :3]
    var_r = np.diag(R @ C[:3, :3] @ R.T) if np.all(np.isfinite(C)) else np.full(3, np.inf)
    var_t = np.diag(R @ C[3:, 3:] @ R.T) if np.all(np.isfinite(C)) else np.full(3, np.inf)
    weak, axis = weakest_rotation(part_from_cam)
    # flange motions B_j^-1 B_i = X P_j^-1 P_i X^-1 (the artefact's placement cancels)
    P = np.asarray(part_from_cam, dtype=float)
    X = np.asarray(flange_from_cam, dtype=float)
    i, j = np.triu_indices(len(P), 1)
    M = X @ invert(P[j]) @ P[i] @ invert(X)
    L = (np.eye(3) - M[:, :3, :3]).reshape(-1, 3)
    c = np.linalg.lstsq(L, M[:, :3, 3].ravel(), rcond=None)[0]
    pivot = float(np.sqrt(np.mean((L @ c - M[:, :3, 3].ravel()) ** 2))) if len(M) else 0.0
    return HandEyeConditioning(np.sqrt(np.where(var_t >= 0, var_t, np.inf)), np.sqrt(np.where(var_r >= 0, var_r, np.inf)),
                               weak, axis, pivot, int(len(info)))
