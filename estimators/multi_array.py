"""Geometric calibration of distributed, mutually asynchronous microphone arrays.

Implements the maximum-likelihood calibration from source correspondences of
``shared/papers/mle_multi_array_calibration.txt``: each array is internally synchronous with a known
internal geometry; a probe (loudspeaker) is played at ``S`` unknown places; every array localises it in its
own frame from its TDOAs, and the poses of the arrays are found from these correspondences, weighting each
localisation by its anisotropic covariance (precise across the direction of arrival, vague along the range
in the far field). The paper's baseline, the rigid-body method [6], is here too.

Pipeline (paper equation numbers)
---------------------------------
1. :func:`localize_spherical_ls`, eqs. (3)-(6): spherical least squares from one array's TDOAs against its
   reference mic, ``theta = (A^T A)^-1 A^T b`` with ``A = [S | Delta]``, ``theta = [X^T, |X - Y_1|]^T``,
   vectorised over sources; by default (not in the paper) TDOAs inconsistent with the others (wrong GCC
   peaks) are dropped first.
2. :func:`localization_covariance`, eq. (13): the CRLB ``I(X)^-1`` with ``I = G G^T / (sigma c)^2``, evaluated
   at the estimate and kept fixed, as the paper does.
3. :func:`rigid_body_ransac`: Kabsch/Umeyama SVD (:func:`rigid_transform`) on 3-point samples inside RANSAC
   (least-median-of-squares scoring unless a threshold is given), then a refit on the inliers: the
   rigid-body method [6] and the MLE's initial value.
4. :func:`refine_mle`: the alternating maximisation of the likelihood (9). Step 1 fuses every source over the
   arrays by eq. (15) (with ``K > 2`` arrays, the information-weighted mean over all of them); step 2 updates
   the poses by nonlinear least squares on the Mahalanobis distances of eq. (17) (whitened residuals,
   Levenberg-Marquardt on a rotation increment and the translation). Repeat until the poses move by less than
   the tolerances. The paper's step 2 holds the fused sources fixed (``pose_step="paper"``); that
   block-coordinate descent needs thousands of alternations in the far field (measured: ~2000 at d = 6 m), so
   by default (``pose_step="schur"``) step 2 is one Gauss-Newton step whose normal equations include how the
   fused sources move with the poses (sources eliminated by the Schur complement): the same fixed point in
   about ten alternations.
5. :func:`calibrate_arrays` (TDOAs in) and :func:`calibrate_from_locations` (localisations in) chain these;
   with more than two arrays each one is first calibrated against the reference array, then all poses are
   refined jointly (shared fused sources).

Robustness. With ``robust=True`` (default) the MLE first runs with Cauchy weights ``1 / (1 + d2 / (v q95))``
on each source's fused Mahalanobis distance ``d2`` (``v``: variance factor from the median over all probes,
``q95``: the chi-square 95 % point, ``dof = 3 (n_arrays_seeing_it - 1)``), then rejects every probe with
``d2 > v chi2_dof(reject_quantile)`` and re-solves without weights on the rest until the rejected set is
stable. A rejected probe is dropped for all arrays. Rejected probes are reported
(:attr:`MultiArrayCalibration.rejected_sources`).

Uncertainty. The pose covariance is the inverse of the Gauss-Newton information of all poses with the
source positions eliminated (Schur complement), scaled by the a-posteriori variance factor
``sum d2 / dof`` (:attr:`MultiArrayCalibration.variance_factor`, about 1 when ``sigma_tdoa_s`` and the
CRLB describe the localisation errors; the CRLB is optimistic for the spherical least-squares estimator in the
far field, so expect more). The rigid-body method gets the same treatment with isotropic covariances.

Conventions (this module)
-------------------------
- Mic positions ``(n_mics, 3)`` in metres in the array's own local frame; ``reference_mic`` (default 0) is the
  TDOA reference. ``tdoa_s[s, m] = toa[m] - toa[ref]`` for source ``s`` (seconds; :mod:`estimators.conventions`
  ``tdoa[m, ref]``); the reference column is ignored; NaN marks a TDOA that was not measured.
- Localisations ``(n_sources, 3)`` in metres in each array's local frame; a NaN row is a probe the array missed.
- Pose of array ``k``: ``x_ref = R_k @ x_k + t_k`` maps its local coordinates into the reference array's frame,
  so ``translation_m`` is the position of array ``k``'s local origin (its reference mic, for the paper's
  frames) and the columns of ``R_k`` are its axes. This is the direction of the paper's eq. (15), where
  ``R X'' + t`` expresses the second array's estimate in the first array's frame; the paper's eq. (7)
  writes the inverse map. ``rotation_deg = (roll, pitch, yaw)`` with ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
- Errors (eqs. 18-19): ``eps_R = arccos((tr(R_est^T R) - 1) / 2)``, ``eps_t = arccos(t_est^T t / |t_est||t|)``,
  both in degrees, and ``|t_est - t|`` in metres.

Bad input raises a :class:`CalibrationInputError` (a ``ValueError``) with one sentence: too few mics or
sources, mics collinear or coplanar (no 3-D localisation), sources collinear or all in one direction, far-field
sources coplanar with both arrays (bearings cannot fix the pose), and, after the solve, a pose the sources do
not determine (rotation standard deviation above ``max_rotation_std_deg``) or localisations that disagree far
beyond their stated noise (variance factor above ``max_variance_factor``: unreliable TDOAs). Coplanar
source sets are accepted in the near field: three non-collinear correspondences fix a rigid motion.

Imports numpy and scipy only.
"""
from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from typing import Literal

import numpy as np
import scipy.stats
from scipy.spatial.transform import Rotation

from .conventions import SPEED_OF_SOUND_M_S

__all__ = [
    "ArrayPose",
    "CalibrationInputError",
    "DegenerateArrayError",
    "DegenerateSourcesError",
    "InconsistentDataError",
    "MultiArrayCalibration",
    "TooFewSourcesError",
    "UnobservablePoseError",
    "calibrate_arrays",
    "calibrate_from_locations",
    "localization_covariance",
    "localize_spherical_ls",
    "refine_mle",
    "rigid_body_ransac",
    "rigid_transform",
    "rotation_deg_from_matrix",
    "rotation_error_deg",
    "rotation_matrix_from_deg",
    "translation_angle_error_deg",
    "paper_array_m",
    "paper_scene",
]

log = logging.getLogger(__name__)

Method = Literal["mle", "rigid_body"]
PoseStep = Literal["schur", "paper"]

MIN_SOURCES = 4
"""Correspondences needed per array pair: 3 fix a rigid motion, the 4th makes outliers detectable."""
MIN_MICS = 5
"""Mics per array: eq. (6) has 4 unknowns and needs ``M - 1 >= 4`` TDOAs against the reference."""

# Relative singular-value floor below which a point set counts as lower-dimensional (collinear / coplanar).
_RANK_REL_TOL = 1e-3
# Smallest variance factor used for weights and rejection (d2 below 1e-6 is agreement to rounding, not noise).
_MIN_VARIANCE_FACTOR = 1e-6
# Cauchy weights of the robust phase: scale at the chi-square 95 % point of each source's distance.
_CAUCHY_QUANTILE = 0.95


# ----------------------------------------------------------------------------------------------------- errors
class CalibrationInputError(ValueError):
    """Input from which multi-array calibration cannot determine a pose."""


class TooFewSourcesError(CalibrationInputError):
    """Fewer probe correspondences (or mics) than the problem needs."""


class DegenerateSourcesError(CalibrationInputError):
    """The probe positions are degenerate: collinear or all in one direction."""


class DegenerateArrayError(CalibrationInputError):
    """An array's mics cannot localise in 3-D (too few, collinear or coplanar)."""


class UnobservablePoseError(DegenerateSourcesError):
    """After the solve, the correspondences do not determine the pose (near-singular information)."""


class InconsistentDataError(CalibrationInputError):
    """The localisations disagree with each other far beyond their stated uncertainty (unreliable TDOAs)."""


# -------------------------------------------------------------------------------------------------- rotations
def rotation_matrix_from_deg(rotation_deg) -> np.ndarray:
    """Rotation matrix from roll, pitch, yaw: ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

    Parameters
    ----------
    rotation_deg : array_like, shape (3,) or (n, 3), float
        ``(roll, pitch, yaw)`` in degrees.

    Returns
    -------
    ndarray, shape (3, 3) or (n, 3, 3), float64
    """
    a = np.asarray(rotation_deg, dtype=float)
    return Rotation.from_euler("ZYX", a[..., ::-1], degrees=True).as_matrix()


def rotation_deg_from_matrix(rotation_matrix) -> np.ndarray:
    """Roll, pitch, yaw in degrees of ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (inverse of
    :func:`rotation_matrix_from_deg`; pitch in [-90, 90])."""
    return Rotation.from_matrix(np.asarray(rotation_matrix, float)).as_euler("ZYX", degrees=True)[..., ::-1]


def rotation_error_deg(rotation_estimate, rotation_true) -> np.ndarray:
    """Eq. (18): angle of ``R_est^T R`` in exponential coordinates, ``arccos((tr(R_est^T R) - 1) / 2)``, degrees.

    Broadcasts over leading dimensions of ``(..., 3, 3)`` inputs.
    """
    Re, Rt = np.asarray(rotation_estimate, float), np.asarray(rotation_true, float)
    # the same angle as the magnitude of the rotation vector of Re^T Rt: arccos loses precision near 0
    rel = np.swapaxes(Re, -1, -2) @ Rt
    return np.degrees(Rotation.from_matrix(rel.reshape(-1, 3, 3)).magnitude()).reshape(rel.shape[:-2])


def translation_angle_error_deg(translation_estimate_m, translation_true_m) -> np.ndarray:
    """Eq. (19): angle between the estimated and true translation directions, ``arccos(t_est^T t)`` on unit
    vectors, degrees. Broadcasts over leading dimensions of ``(..., 3)`` inputs."""
    a, b = np.asarray(translation_estimate_m, float), np.asarray(translation_true_m, float)
    # atan2(|a x b|, a.b): the angle of eq. (19), precise near 0 and 180 deg; NaN for a zero vector
    with np.errstate(invalid="ignore", divide="ignore"):
        zero = (np.linalg.norm(a, axis=-1) == 0) | (np.linalg.norm(b, axis=-1) == 0)
        angle = np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, -1)))
    return np.where(zero, np.nan, angle)


def _skew(v: np.ndarray) -> np.ndarray:
    """``[v]_x`` with ``[v]_x u = v x u``; ``v`` shape (..., 3) -> (..., 3, 3)."""
    z = np.zeros(v.shape[:-1])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1),
                     np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def _exp_so3(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation matrix of a rotation vector (radians), shape (3,) -> (3, 3)."""
    angle = float(np.linalg.norm(rotvec))
    K = _skew(rotvec)
    if angle < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(angle) / angle * K + (1.0 - np.cos(angle)) / angle**2 * K @ K


# ----------------------------------------------------------------------------------------------------- results
def _frozen(a, *, shape=None, name="array", dtype=np.float64) -> np.ndarray:
    out = np.array(a, dtype=dtype, copy=True)
    if shape is not None and out.shape != shape:
        raise ValueError(f"{name} has shape {out.shape}, expected {shape}")
    out.setflags(write=False)
    return out


@dataclasses.dataclass(frozen=True, eq=False)
class ArrayPose:
    """Pose of one array in the reference array's frame: ``x_ref = rotation_matrix @ x_local + translation_m``.

    Attributes
    ----------
    rotation_matrix : ndarray, shape (3, 3), float64
        Orthonormal, det +1; its columns are the array's axes in the reference frame.
    translation_m : ndarray, shape (3,), float64
        Position of the array's local origin in the reference frame, metres.
    rotation_std_deg : ndarray, shape (3,), float64
        Standard deviation of small rotations about the reference frame's x, y, z axes, degrees (0 for the
        reference array).
    translation_std_m : ndarray, shape (3,), float64
        Standard deviation of ``translation_m``, metres.
    covariance : ndarray, shape (6, 6), float64
        Covariance of ``(rotation increment in radians about the reference axes, translation in metres)``,
        scaled by the a-posteriori variance factor; all ``inf`` where the information is singular.
    rotation_deg : ndarray, shape (3,), float64
        ``(roll, pitch, yaw)`` in degrees of ``rotation_matrix`` (derived).
    """

    rotation_matrix: np.ndarray
    translation_m: np.ndarray
    rotation_std_deg: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    translation_std_m: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    covariance: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((6, 6)))
    rotation_deg: np.ndarray = dataclasses.field(init=False)

    def __post_init__(self):
        R = _frozen(self.rotation_matrix, shape=(3, 3), name="rotation_matrix")
        if not (np.allclose(R.T @ R, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0):
            raise ValueError("rotation_matrix must be orthonormal with det +1")
        object.__setattr__(self, "rotation_matrix", R)
        object.__setattr__(self, "translation_m", _frozen(self.translation_m, shape=(3,), name="translation_m"))
        object.__setattr__(self, "rotation_std_deg", _frozen(self.rotation_std_deg, shape=(3,),
                                                             name="rotation_std_deg"))
        object.__setattr__(self, "translation_std_m", _frozen(self.translation_std_m, shape=(3,),
                                                              name="translation_std_m"))
        object.__setattr__(self, "covariance", _frozen(self.covariance, shape=(6, 6), name="covariance"))
        object.__setattr__(self, "rotation_deg", _frozen(rotation_deg_from_matrix(R)))

    @classmethod
    def identity(cls) -> ArrayPose:
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_deg(cls, rotation_deg, translation_m) -> ArrayPose:
        """Pose from ``(roll, pitch, yaw)`` in degrees and a translation in metres."""
        return cls(rotation_matrix_from_deg(rotation_deg), translation_m)

    def to_reference(self, points_m) -> np.ndarray:
        """Map ``(..., 3)`` points (metres) from this array's frame into the reference frame."""
        return np.asarray(points_m, float) @ self.rotation_matrix.T + self.translation_m

    def from_reference(self, points_m) -> np.ndarray:
        """Map ``(..., 3)`` points (metres) from the reference frame into this array's frame."""
        return (np.asarray(points_m, float) - self.translation_m) @ self.rotation_matrix

    def errors(self, truth: ArrayPose) -> dict[str, float]:
        """Eqs. (18)-(19) against ``truth``: ``rotation_deg`` (eps_R), ``translation_angle_deg`` (eps_t),
        ``translation_m`` (``|t_est - t|``)."""
        return {
            "rotation_deg": float(rotation_error_deg(self.rotation_matrix, truth.rotation_matrix)),
            "translation_angle_deg": float(translation_angle_error_deg(self.translation_m, truth.translation_m)),
            "translation_m": float(np.linalg.norm(self.translation_m - truth.translation_m)),
        }


@dataclasses.dataclass(frozen=True, eq=False)
class MultiArrayCalibration:
    """Outcome of :func:`calibrate_arrays` / :func:`calibrate_from_locations` / :func:`refine_mle` (immutable).

    Attributes
    ----------
    poses : tuple of ArrayPose
        One per array, in input order; the reference array's is the identity.
    reference_array : int
    method : {"mle", "rigid_body"}
    fused_sources_m : ndarray, shape (n_sources, 3), float64
        Probe positions in the reference frame: eq. (15) fused over the arrays (``"mle"``) or the mean of the
        mapped localisations (``"rigid_body"``); NaN where fewer than two arrays localised the probe.
    rejected_sources : tuple of int
        Probes left out as outliers (robust MLE: fused Mahalanobis distance above the rejection quantile;
        rigid body: RANSAC outliers against any array).
    variance_factor : float
        A-posteriori variance factor ``sum d2 / dof`` over the kept probes (``d2``: eq. (17) terms at the fused
        positions); about 1 when ``sigma_tdoa_s`` and the CRLB model are right. The pose covariances include it.
    cost : float
        Eq. (17) at the solution over the kept probes (sum of squared Mahalanobis distances, dimensionless;
        with unit isotropic covariances for ``"rigid_body"``: squared metres).
    n_iterations : int
        Alternations of steps 1-2 (all rounds; 0 for ``"rigid_body"``).
    converged : bool
        The last round met the pose tolerances within ``max_iterations``.
    sigma_tdoa_s : float or None
        TDOA noise std the covariances assume, seconds (None when covariances were given).
    speed_of_sound_m_s : float or None
    """

    poses: tuple[ArrayPose, ...]
    reference_array: int
    method: Method
    fused_sources_m: np.ndarray
    rejected_sources: tuple[int, ...]
    variance_factor: float
    cost: float
    n_iterations: int
    converged: bool
    sigma_tdoa_s: float | None = None
    speed_of_sound_m_s: float | None = None

    def __post_init__(self):
        object.__setattr__(self, "fused_sources_m", _frozen(self.fused_sources_m))
        object.__setattr__(self, "poses", tuple(self.poses))
        object.__setattr__(self, "rejected_sources", tuple(int(i) for i in self.rejected_sources))


# ---------------------------------------------------------------------------------------------- localisation
def _check_mics(mic_positions_m, reference_mic: int, *, name: str = "array") -> np.ndarray:
    mics = np.asarray(mic_positions_m, dtype=float)
    if mics.ndim != 2 or mics.shape[1] != 3:
        raise ValueError(f"mic_positions_m of {name} has shape {mics.shape}; expected (n_mics, 3) metres")
    if not np.all(np.isfinite(mics)):
        raise ValueError(f"mic_positions_m of {name} must be finite (metres)")
    n_mics = mics.shape[0]
    if n_mics < MIN_MICS:
        raise DegenerateArrayError(f"{name} has {n_mics} mics; 3-D spherical least squares needs >= {MIN_MICS}")
    if not 0 <= reference_mic < n_mics:
        raise ValueError(f"{reference_mic=} must be in 0..{n_mics - 1} for {name}")
    sv = np.linalg.svd(mics - mics.mean(0), compute_uv=False)
    if sv[0] <= 0.0:
        raise DegenerateArrayError(f"all mics of {name} are at one point; it cannot localise")
    if sv[1] < _RANK_REL_TOL * sv[0]:
        raise DegenerateArrayError(f"the mics of {name} are collinear; it cannot localise in 3-D "
                                   "(a line array only measures the angle to its axis)")
    if sv[2] < _RANK_REL_TOL * sv[0]:
        raise DegenerateArrayError(f"the mics of {name} are coplanar; it cannot localise in 3-D "
                                   "(mirror ambiguity about its plane, eq. (6) is singular)")
    return mics


def _weighted_spherical_ls(Y: np.ndarray, delta: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Eq. (6) with per-equation weights: ``theta = argmin |sqrt(w) (A theta - b)|``, through the SVD.

    ``Y`` (M-1, 3) mics relative to the reference, ``delta`` (n, M-1) range differences in metres (finite),
    ``w`` (n, M-1) >= 0. Returns ``theta`` (n, 4); NaN rows where fewer than 4 weights are positive.
    """
    A = np.concatenate([np.broadcast_to(Y, delta.shape + (3,)), delta[..., None]], axis=2)  # eq. (5)
    b = 0.5 * (np.sum(Y * Y, axis=1) - delta * delta)  # eq. (5)
    sw = np.sqrt(w)
    U, s, Vt = np.linalg.svd(A * sw[..., None], full_matrices=False)
    s_inv = np.where(s > 1e-12 * s[:, :1], 1.0 / np.where(s > 0, s, 1.0), 0.0)
    theta = np.einsum("nji,nj->ni", Vt, s_inv * np.einsum("nmj,nm->nj", U, sw * b))  # eq. (6)
    theta[np.count_nonzero(w > 0, axis=1) < 4] = np.nan
    return theta


def _range_difference_residual_m(Y: np.ndarray, delta: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``(|Y_m - X| - |X|) - Delta_m`` in metres (reference mic at the origin), shape (n, M-1)."""
    return np.linalg.norm(Y[None] - X[:, None], axis=-1) - np.linalg.norm(X, axis=-1)[:, None] - delta


_N_SUBSETS = 32
_SUBSET_SIZE = 5
# A probe whose RMS range-difference residual exceeds this many times the array's median is not localised.
_FAILED_RMS_RATIO = 10.0


def _lmeds_start(Y: np.ndarray, delta: np.ndarray, valid: np.ndarray, theta_all: np.ndarray) -> np.ndarray:
    """Least median of squares over fixed random 5-TDOA subsets (and all of them): the solution whose
    range-difference residuals over all TDOAs have the smallest median. One wrong GCC peak among 17 TDOAs
    can drag eq. (6) anywhere; a subset without it cannot be dragged."""
    n, m = delta.shape
    if m <= _SUBSET_SIZE:
        return theta_all
    pick = np.random.default_rng(0).random((_N_SUBSETS, m)).argsort(1)[:, :_SUBSET_SIZE]  # deterministic
    mask = np.zeros((_N_SUBSETS, m), bool)
    np.put_along_axis(mask, pick, True, axis=1)
    w = (valid[:, None, :] & mask[None]).reshape(-1, m).astype(float)
    theta = _weighted_spherical_ls(Y, np.repeat(delta, _N_SUBSETS, 0), w).reshape(n, _N_SUBSETS, 4)
    theta = np.concatenate([theta_all[:, None], theta], axis=1)
    r = np.abs(np.linalg.norm(Y[None, None] - np.nan_to_num(theta[..., None, :3]), axis=-1)
               - np.linalg.norm(np.nan_to_num(theta[..., :3]), axis=-1)[..., None] - delta[:, None])
    med = np.nanmedian(np.where(valid[:, None], r, np.nan), axis=-1)
    med = np.where(np.all(np.isfinite(theta), -1), med, np.inf)
    return theta[np.arange(n), np.argmin(med, axis=1)]


def localize_spherical_ls(tdoa_s, mic_positions_m, *, speed_of_sound_m_s: float = SPEED_OF_SOUND_M_S,
                          reference_mic: int = 0, reject_outliers: bool = True, return_inliers: bool = False):
    """Source positions from one array's TDOAs by spherical least squares, eqs. (3)-(6).

    With the reference mic ``Y_1`` at the origin, ``Delta_m = c tdoa_m`` (eq. 2) and
    ``|Y_m - X| = |X| + Delta_m`` squared give ``Y_m^T X + Delta_m |X| = (|Y_m|^2 - Delta_m^2) / 2``:
    ``A theta = b`` with ``A = [S | Delta]``, ``S = [Y_2 ... Y_M]^T``, ``theta = [X^T, |X - Y_1|]^T`` (eq. 5), and
    ``theta = (A^T A)^-1 A^T b`` (eq. 6), computed through the SVD of ``A`` (the same solution, better
    conditioned in the far field where the ``Delta`` column nearly lies in the span of ``S``). The constraint
    ``theta_4 = |theta_1:3|`` is not imposed, as in the paper.

    ``reject_outliers`` (not in the paper): one TDOA from a wrong GCC peak moves the estimate by metres. Start
    from the least-median-of-squares solution over 32 fixed random subsets of 5 TDOAs (and all TDOAs), re-weight
    (Cauchy weights on the range-difference residuals ``|Y_m - X| - |X| - Delta_m`` scaled by ``1.4826 MAD``,
    floored at 10 um) for 10 iterations, then drop the TDOAs with residuals above 3.5 scales and solve eq. (6)
    on the rest. A probe whose RMS residual then still exceeds 10 times the median over the probes (with >= 3
    probes) is returned as NaN, not localised: most of its TDOAs are wrong and its estimate sits next to the
    array, where the CRLB would call it precise. On consistent TDOAs nothing is dropped and the result is
    eq. (6).

    Parameters
    ----------
    tdoa_s : ndarray, shape (n_sources, n_mics) or (n_mics,), float
        ``toa[m] - toa[reference_mic]`` in seconds; the reference column is ignored; NaN entries are left out
        (a source with fewer than 4 finite TDOAs gives NaN).
    mic_positions_m : ndarray, shape (n_mics, 3), float
        Mic positions in the array's local frame, metres; at least 5 mics, not coplanar.
    speed_of_sound_m_s : float
    reference_mic : int
    reject_outliers : bool
    return_inliers : bool
        Also return which TDOAs were used.

    Returns
    -------
    positions_m : ndarray, shape (n_sources, 3) or (3,), float64
        Source positions in the array's local frame, metres.
    inliers : ndarray, shape (n_sources, n_mics) or (n_mics,), bool
        Only with ``return_inliers``: TDOAs used (the reference column is True).

    Raises
    ------
    DegenerateArrayError
        Fewer than 5 mics, or mics collinear or coplanar.
    """
    mics = _check_mics(mic_positions_m, reference_mic)
    if not speed_of_sound_m_s > 0:
        raise ValueError(f"{speed_of_sound_m_s=} must be > 0 (m/s)")
    tdoa = np.asarray(tdoa_s, dtype=float)
    single = tdoa.ndim == 1
    tdoa = np.atleast_2d(tdoa)
    n_mics = mics.shape[0]
    if tdoa.ndim != 2 or tdoa.shape[1] != n_mics:
        raise ValueError(f"tdoa_s has shape {np.shape(tdoa_s)}; expected (n_sources, {n_mics}) seconds")
    others = np.delete(np.arange(n_mics), reference_mic)
    Y = mics[others] - mics[reference_mic]  # S of eq. (5), reference mic at the origin
    delta = speed_of_sound_m_s * tdoa[:, others]  # eq. (2): range differences, metres
    valid = np.isfinite(delta)
    delta = np.where(valid, delta, 0.0)
    w = valid.astype(float)
    theta = _weighted_spherical_ls(Y, delta, w)
    if reject_outliers:
        theta = _lmeds_start(Y, delta, valid, theta)
        for _ in range(10):
            r = _range_difference_residual_m(Y, delta, np.nan_to_num(theta[:, :3]))
            scale = 1.4826 * np.nanmedian(np.where(valid, np.abs(r), np.nan), axis=1, keepdims=True)
            scale = np.maximum(np.nan_to_num(scale), 1e-5)
            theta = _weighted_spherical_ls(Y, delta, valid / (1.0 + (r / (2.385 * scale)) ** 2))  # Cauchy IRLS
        r = _range_difference_residual_m(Y, delta, np.nan_to_num(theta[:, :3]))
        w = (valid & (np.abs(r) <= 3.5 * scale)).astype(float)
        theta = _weighted_spherical_ls(Y, delta, w)
        # a probe whose kept TDOAs still disagree (most of them wrong: it collapses next to the array with a
        # confident CRLB) is not localised
        r = _range_difference_residual_m(Y, delta, np.nan_to_num(theta[:, :3]))
        rms = np.sqrt(np.sum(w * r * r, axis=1) / np.maximum(np.sum(w, axis=1), 1))
        ok = np.all(np.isfinite(theta), axis=1)
        if np.count_nonzero(ok) >= 3:
            failed = ok & (rms > _FAILED_RMS_RATIO * max(float(np.median(rms[ok])), 1e-5))
            theta[failed] = np.nan
            w[failed] = 0.0
    out = theta[:, :3] + mics[reference_mic]
    if not return_inliers:
        return out[0] if single else out
    inliers = np.ones(tdoa.shape, bool)
    inliers[:, others] = w > 0
    return (out[0], inliers[0]) if single else (out, inliers)


def _regularised_inverse(info: np.ndarray, rcond: float) -> np.ndarray:
    """Inverse of symmetric PSD ``(..., 3, 3)`` matrices with eigenvalues floored at ``rcond * max``."""
    lam, V = np.linalg.eigh(info)
    floor = rcond * np.maximum(lam[..., -1:], np.finfo(float).tiny)
    return np.einsum("...ij,...j,...kj->...ik", V, 1.0 / np.maximum(lam, floor), V)


def localization_covariance(source_positions_m, mic_positions_m, *, sigma_tdoa_s: float,
                            speed_of_sound_m_s: float = SPEED_OF_SOUND_M_S, reference_mic: int = 0,
                            tdoa_used=None, rcond: float = 1e-10) -> np.ndarray:
    """CRLB covariance of TDOA localisation at the given source positions, eq. (13).

    ``I(X) = G G^T / (sigma c)^2`` with columns ``g_m - g_ref`` of ``G``, ``g_i = (X - X_i) / |X - X_i|``: the
    Fisher information of the ``M - 1`` TDOAs against the reference mic with independent errors of std
    ``sigma_tdoa_s``. Returns ``I^-1``; where ``I`` is near-singular (a source very far away, or on a mic) its
    eigenvalues are floored at ``rcond`` times the largest before inverting, i.e. the vaguest direction (the
    range, in the far field) gets at most ``1 / sqrt(rcond)`` times the std of the sharpest one. The paper
    evaluates this at the estimated position and keeps it fixed (``Sigma(X) ~ Sigma_bar(X_hat)``).

    Parameters
    ----------
    source_positions_m : ndarray, shape (n_sources, 3) or (3,), float
        In the array's local frame, metres; NaN rows give NaN covariances.
    mic_positions_m : ndarray, shape (n_mics, 3), float
    sigma_tdoa_s : float
        TDOA noise standard deviation, seconds (the paper states it in samples: divide by the rate).
    speed_of_sound_m_s : float
    reference_mic : int
    tdoa_used : ndarray, shape (n_sources, n_mics) or (n_mics,), bool, optional
        TDOAs the localisation used (``localize_spherical_ls(..., return_inliers=True)``); default all.
    rcond : float
        Eigenvalue floor of ``I`` relative to its largest eigenvalue.

    Returns
    -------
    ndarray, shape (n_sources, 3, 3) or (3, 3), float64
        Covariance in square metres, in the array's local frame.
    """
    mics = _check_mics(mic_positions_m, reference_mic)
    if not (np.isfinite(sigma_tdoa_s) and sigma_tdoa_s > 0):
        raise ValueError(f"{sigma_tdoa_s=} must be a finite number > 0 (seconds)")
    if not 0 < rcond < 1:
        raise ValueError(f"{rcond=} must be in (0, 1)")
    X = np.asarray(source_positions_m, dtype=float)
    single = X.ndim == 1
    X = np.atleast_2d(X)
    if X.shape[-1] != 3:
        raise ValueError(f"source_positions_m has shape {np.shape(source_positions_m)}; expected (n_sources, 3)")
    diff = X[:, None, :] - mics[None]  # X - X_i
    g = diff / np.maximum(np.linalg.norm(diff, axis=-1, keepdims=True), 1e-12)  # g_i of eq. (13)
    others = np.delete(np.arange(mics.shape[0]), reference_mic)
    G = g[:, others] - g[:, [reference_mic]]  # g_m - g_ref, (n, M-1, 3)
    if tdoa_used is not None:
        used = np.atleast_2d(np.asarray(tdoa_used, bool))
        if used.shape != (X.shape[0], mics.shape[0]):
            raise ValueError(f"tdoa_used has shape {np.shape(tdoa_used)}; expected ({X.shape[0]}, {mics.shape[0]})")
        G = G * used[:, others, None]
    info = np.einsum("nmi,nmj->nij", G, G) / (sigma_tdoa_s * speed_of_sound_m_s) ** 2  # eq. (13)
    ok = np.all(np.isfinite(X), axis=1)
    cov = np.full(info.shape, np.nan)
    if np.any(ok):
        cov[ok] = _regularised_inverse(info[ok], rcond)
    return cov[0] if single else cov


# ------------------------------------------------------------------------------------------ rigid body (RBM)
def _kabsch(P: np.ndarray, Q: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Batched weighted Kabsch/Umeyama without scale: ``argmin sum w |Q - (R P + t)|^2``.

    ``P, Q`` shape (..., n, 3), ``w`` (..., n) or None. Returns ``R`` (..., 3, 3) with det +1 and ``t`` (..., 3).
    """
    if w is None:
        w = np.ones(P.shape[:-1])
    w = w / np.sum(w, axis=-1, keepdims=True)
    mp = np.einsum("...n,...ni->...i", w, P)
    mq = np.einsum("...n,...ni->...i", w, Q)
    H = np.einsum("...n,...ni,...nj->...ij", w, P - mp[..., None, :], Q - mq[..., None, :])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    d = np.where(d == 0, 1.0, d)
    D = np.broadcast_to(np.eye(3), H.shape).copy()
    D[..., 2, 2] = d
    R = np.swapaxes(Vt, -1, -2) @ D @ np.swapaxes(U, -1, -2)
    t = mq - np.einsum("...ij,...j->...i", R, mp)
    return R, t


def rigid_transform(points_from_m, points_to_m, weights=None) -> ArrayPose:
    """Least-squares rigid motion by SVD (Kabsch/Umeyama without scale, ref. [10] of the paper).

    Finds ``R, t`` minimising ``sum_s w_s |to_s - (R from_s + t)|^2`` with ``det R = +1`` (a reflection in the
    SVD solution is flipped on the smallest singular direction, so coplanar point sets are handled).

    Parameters
    ----------
    points_from_m, points_to_m : ndarray, shape (n_points, 3), float
        Corresponding points, metres; ``n_points >= 3``, not collinear.
    weights : ndarray, shape (n_points,), float, optional

    Returns
    -------
    ArrayPose
        ``to ~ pose.to_reference(from)``.
    """
    P, Q = np.asarray(points_from_m, float), np.asarray(points_to_m, float)
    if P.shape != Q.shape or P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"points must both be (n_points, 3) metres; got {P.shape} and {Q.shape}")
    if P.shape[0] < 3:
        raise TooFewSourcesError(f"a rigid motion needs >= 3 corresponding points; got {P.shape[0]}")
    _check_source_shape(P, "points_from_m")
    w = None if weights is None else np.asarray(weights, float)
    R, t = _kabsch(P, Q, w)
    return ArrayPose(R, t)


def _triangle_area2(P: np.ndarray) -> np.ndarray:
    """Squared area (times 4) of triangles ``P`` of shape (..., 3, 3)."""
    return np.sum(np.cross(P[..., 1, :] - P[..., 0, :], P[..., 2, :] - P[..., 0, :]) ** 2, axis=-1)


def rigid_body_ransac(points_reference_m, points_array_m, *, rng: np.random.Generator | int = 0,
                      n_hypotheses: int = 256, threshold_m: float | None = None) -> tuple[ArrayPose, np.ndarray]:
    """Rigid-body method [6]: Kabsch on random 3-point samples inside RANSAC, then a refit on the inliers.

    Each hypothesis maps the array's localisations onto the reference's; the residual of a probe is
    ``|x_ref - (R x_array + t)|`` in metres. With ``threshold_m=None`` a hypothesis is scored by the median
    squared residual (least median of squares, no threshold to tune) and the inliers are the residuals below
    ``2.5 * 1.4826 (1 + 5 / (n - 3)) sqrt(median)`` (Rousseeuw's robust scale); with a threshold, by the
    truncated squared residual (MSAC) and the inliers are the residuals below it.

    Parameters
    ----------
    points_reference_m, points_array_m : ndarray, shape (n_sources, 3), float
        The same probes localised by the reference array and by the other array, each in its own frame,
        metres; rows with a NaN in either are ignored.
    rng : numpy.random.Generator or int
        Sample source (an int seeds a new generator).
    n_hypotheses : int
    threshold_m : float or None

    Returns
    -------
    pose : ArrayPose
        Pose of the array in the reference frame (no covariance).
    inliers : ndarray, shape (n_sources,), bool
    """
    Q, P = np.asarray(points_reference_m, float), np.asarray(points_array_m, float)
    if Q.shape != P.shape or Q.ndim != 2 or Q.shape[1] != 3:
        raise ValueError(f"localisations must both be (n_sources, 3) metres; got {Q.shape} and {P.shape}")
    if n_hypotheses < 1:
        raise ValueError(f"{n_hypotheses=} must be >= 1")
    if threshold_m is not None and not threshold_m > 0:
        raise ValueError(f"{threshold_m=} must be > 0 metres or None")
    rng = np.random.default_rng(rng)
    valid = np.all(np.isfinite(P), 1) & np.all(np.isfinite(Q), 1)
    idx = np.flatnonzero(valid)
    n = idx.size
    if n < MIN_SOURCES:
        raise TooFewSourcesError(f"{n} probes localised by both arrays; calibration needs >= {MIN_SOURCES}")
    Pv, Qv = P[idx], Q[idx]
    scale2 = np.sum((Pv - Pv.mean(0)) ** 2) / n
    keys = rng.random((n_hypotheses, n))
    samples = np.argpartition(keys, 2, axis=1)[:, :3]
    ok = _triangle_area2(Pv[samples]) > 1e-6 * scale2**2  # drop (near-)collinear triples
    samples = samples[ok] if np.any(ok) else samples
    R, t = _kabsch(Pv[samples], Qv[samples])
    r2 = np.sum((Qv[None] - (np.einsum("hij,nj->hni", R, Pv) + t[:, None])) ** 2, axis=-1)  # (H, n)

    def inliers_of(r2_row: np.ndarray) -> np.ndarray:
        if threshold_m is None:
            sigma = 1.4826 * (1.0 + 5.0 / max(n - 3, 1)) * np.sqrt(np.median(r2_row))
            return r2_row <= (2.5 * sigma) ** 2 + 1e-18
        return r2_row <= threshold_m**2

    if threshold_m is None:
        best = int(np.argmin(np.median(r2, axis=1)))
    else:
        best = int(np.argmin(np.sum(np.minimum(r2, threshold_m**2), axis=1)))
    inl = inliers_of(r2[best])
    Rb, tb = R[best], t[best]
    for _ in range(2):  # refit on the inliers, re-select once
        if np.count_nonzero(inl) < 3 or _triangle_area2(_extreme_triangle(Pv[inl])) <= 1e-9 * scale2**2:
            break
        Rb, tb = _kabsch(Pv[inl], Qv[inl])
        inl = inliers_of(np.sum((Qv - (Pv @ Rb.T + tb)) ** 2, axis=-1))
    mask = np.zeros(P.shape[0], bool)
    mask[idx[inl]] = True
    return ArrayPose(Rb, tb), mask


def _extreme_triangle(P: np.ndarray) -> np.ndarray:
    """A well-spread triangle of the point set (for a cheap collinearity test), shape (3, 3)."""
    c = P.mean(0)
    i = int(np.argmax(np.sum((P - c) ** 2, 1)))
    j = int(np.argmax(np.sum((P - P[i]) ** 2, 1)))
    u = P[j] - P[i]
    k = int(np.argmax(np.sum(np.cross(P - P[i], u) ** 2, 1)))
    return P[[i, j, k]]


# -------------------------------------------------------------------------------------------- input checks
def _check_source_shape(points: np.ndarray, name: str) -> None:
    """Raise if the (finite) points are collinear or coincident."""
    sv = np.linalg.svd(points - points.mean(0), compute_uv=False)
    if sv[0] <= 0 or sv[1] < _RANK_REL_TOL * sv[0]:
        raise DegenerateSourcesError(f"the probe positions in {name} are collinear; the rotation about their "
                                     "line is undetermined, place probes off that line")


def _flat_bearings(pts: np.ndarray, cov: np.ndarray) -> tuple[bool, float]:
    """Whether the probes are, within their bearing noise, in one plane through the array's origin (the
    bearings on one great circle), and their median range std (metres).

    Flat means: RMS angle of the bearings out of their best plane through the origin < 3 x the RMS bearing
    std across that plane (from the covariances).
    """
    r = np.linalg.norm(pts, axis=1)
    u = pts / np.maximum(r, 1e-12)[:, None]
    n = np.linalg.svd(u)[2][-1]  # normal of the best plane through the origin
    out_rad = np.sqrt(np.mean((u @ n) ** 2))
    bearing_std_rad = np.sqrt(np.mean(np.einsum("i,sij,j->s", n, cov, n) / np.maximum(r, 1e-12) ** 2))
    range_std_m = float(np.median(np.sqrt(np.einsum("si,sij,sj->s", u, cov, u))))
    return bool(out_rad < 3.0 * bearing_std_rad), range_std_m


def _check_pair(x_ref: np.ndarray, x_k: np.ndarray, k: int, reference_array: int, min_spread_deg: float,
                cov_ref: np.ndarray | None = None, cov_k: np.ndarray | None = None) -> None:
    """Refuse a pair of localisation sets from which the relative pose cannot be determined.

    - fewer than ``MIN_SOURCES`` probes localised by both;
    - all probes within ``min_spread_deg`` of one direction from either array;
    - probes collinear (in either frame);
    - with covariances: probes coplanar with both arrays' origins (bearings of both arrays on a great circle,
      e.g. probes on a line, or probes and arrays all at one height) while the ranges are vague (median range
      std > 10 % of the probes' RMS spread). Two bearings in a plane always intersect, so there the pose would
      rest on the ranges alone; in the near field (precise ranges) such sets are fine.
    """
    both = np.all(np.isfinite(x_ref), 1) & np.all(np.isfinite(x_k), 1)
    n = int(np.count_nonzero(both))
    if n < MIN_SOURCES:
        raise TooFewSourcesError(f"only {n} probes are localised by both array {reference_array} and array {k}; "
                                 f"calibration needs >= {MIN_SOURCES}")
    for arr, pts in ((reference_array, x_ref[both]), (k, x_k[both])):
        u = pts / np.maximum(np.linalg.norm(pts, axis=1, keepdims=True), 1e-12)
        mean = u.mean(0)
        mean /= max(np.linalg.norm(mean), 1e-12)
        spread = float(np.degrees(np.max(np.arccos(np.clip(u @ mean, -1.0, 1.0)))))
        if spread < min_spread_deg:
            raise DegenerateSourcesError(
                f"all {n} probes lie within {spread:.2g} deg of one direction seen from array {arr} "
                f"(< {min_spread_deg=}); spread them out so the rotation about that direction is determined")
        _check_source_shape(pts, f"array {arr}'s frame")
    if cov_ref is None or cov_k is None:
        return
    ok = both & np.all(np.isfinite(cov_ref), (1, 2)) & np.all(np.isfinite(cov_k), (1, 2))
    if np.count_nonzero(ok) < MIN_SOURCES:
        return
    flat_ref, range_ref = _flat_bearings(x_ref[ok], cov_ref[ok])
    flat_k, range_k = _flat_bearings(x_k[ok], cov_k[ok])
    spread_m = float(np.sqrt(np.mean(np.sum((x_ref[ok] - x_ref[ok].mean(0)) ** 2, 1))))
    if flat_ref and flat_k and max(range_ref, range_k) > 0.1 * spread_m:
        raise DegenerateSourcesError(
            f"the probes lie in one plane (or on one line) with both array {reference_array} and array {k} while "
            f"their range std ({max(range_ref, range_k):.2g} m) exceeds 10 % of their spread ({spread_m:.2g} m): "
            "the bearings cannot fix the pose; move some probes out of that plane (e.g. to other heights)")


# ---------------------------------------------------------------------------------------------------- MLE
def _whitening(cov: np.ndarray, max_ratio: float = 1e12) -> np.ndarray:
    """Symmetric ``Sigma^-1/2`` of ``(..., 3, 3)`` covariances (NaN stays NaN); eigenvalues below
    ``max / max_ratio`` are raised to it."""
    out = np.full(cov.shape, np.nan)
    ok = np.all(np.isfinite(cov), axis=(-2, -1))
    if np.any(ok):
        lam, V = np.linalg.eigh(0.5 * (cov[ok] + np.swapaxes(cov[ok], -1, -2)))
        if np.any(lam[:, -1] <= 0):
            raise ValueError("covariances must be positive definite (square metres)")
        lam = np.maximum(lam, lam[:, -1:] / max_ratio)
        out[ok] = np.einsum("nij,nj,nkj->nik", V, 1.0 / np.sqrt(lam), V)
    return out


@dataclasses.dataclass
class _Problem:
    """Arrays of the joint problem: ``K`` arrays, ``S`` probes (mutable solver state lives in the solver)."""

    x: np.ndarray  # (K, S, 3) localisations, local frames (0 where missing)
    W: np.ndarray  # (K, S, 3, 3) whitening Sigma^-1/2, local frames (0 where missing)
    valid: np.ndarray  # (K, S) bool
    reference: int

    @classmethod
    def build(cls, points, covs, reference: int) -> _Problem:
        x = np.stack([np.asarray(p, float) for p in points])
        W = np.stack([_whitening(np.asarray(c, float)) for c in covs])
        valid = np.all(np.isfinite(x), -1) & np.all(np.isfinite(W), (-2, -1))
        return cls(np.where(valid[..., None], x, 0.0), np.where(valid[..., None, None], W, 0.0), valid, reference)


def _fuse(pb: _Problem, R: np.ndarray, t: np.ndarray, active: np.ndarray) -> np.ndarray:
    """Step 1, eq. (15) over all arrays: ``X_F = (sum_k R_k L_k R_k^T)^-1 sum_k R_k L_k (x_k + R_k^T t_k)``,
    ``L_k = Sigma_k^-1``. Probes observed by fewer than two arrays, or inactive, give NaN."""
    L = np.einsum("ksij,ksjl->ksil", pb.W, pb.W)  # Sigma^-1, local frames
    RL = np.einsum("kij,ksjl->ksil", R, L)
    A = np.einsum("ksij,klj->sil", RL, R)  # sum_k R L R^T
    y = pb.x + np.einsum("kji,kj->ki", R, t)[:, None, :]  # x_k + R_k^T t_k
    b = np.einsum("ksij,ksj->si", RL, y)
    n_obs = pb.valid.sum(0)
    ok = active & (n_obs >= 2)
    X = np.full((pb.x.shape[1], 3), np.nan)
    if np.any(ok):
        X[ok] = np.linalg.solve(A[ok], b[ok][..., None])[..., 0]
    return X


def _residuals(pb: _Problem, R: np.ndarray, t: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Whitened residuals ``e_ks = W_ks (x_ks - R_k^T (X_s - t_k))``, shape (K, S, 3); 0 where missing/NaN."""
    q = np.einsum("kji,ksj->ksi", R, X[None] - t[:, None, :])
    e = np.einsum("ksij,ksj->ksi", pb.W, pb.x - q)
    return np.where(pb.valid[..., None] & np.isfinite(e), e, 0.0)


def _fit_pose(pb: _Problem, k: int, R0: np.ndarray, t0: np.ndarray, X: np.ndarray, w: np.ndarray,
              *, max_iterations: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """Step 2 for array ``k``: nonlinear least squares ``min_{R,t} sum_s w_s |W_ks (x_ks - R^T (X_s - t))|^2``.

    Eq. (17) with the fused sources fixed (its first term does not depend on ``R, t``; its second, rotated into
    the array's frame, is ``|Sigma_k^-1/2 (x_k - R^T (X - t))|^2``). Levenberg-Marquardt on a rotation increment
    ``R = Exp(delta) R0`` (radians, about the reference axes; no gimbal lock) and ``t``, Jacobian exact at
    ``delta = 0`` and re-linearised every step.
    """
    use = pb.valid[k] & np.all(np.isfinite(X), 1) & (w > 0)
    W, x, Xs = pb.W[k, use], pb.x[k, use], X[use]
    sw = np.sqrt(w[use])[:, None]
    R, t = R0.copy(), t0.copy()

    def resid(R, t):
        return sw * np.einsum("sij,sj->si", W, x - (Xs - t) @ R)

    e = resid(R, t)
    cost = float(np.sum(e * e))
    mu = 1e-3
    for _ in range(max_iterations):
        p = Xs - t
        WRt = np.einsum("sij,kj->sik", W, R)  # W R^T  (R^T p = p @ R)
        # e = W (x - R^T p): de/ddelta = -W R^T [p]_x, de/dt = W R^T (p = X - t)
        J = np.concatenate([-np.einsum("sij,sjk->sik", WRt, _skew(p)), WRt], axis=2) * sw[..., None]
        J = J.reshape(-1, 6)
        g = J.T @ e.reshape(-1)
        H = J.T @ J
        improved = False
        for _ in range(12):
            step = np.linalg.solve(H + mu * np.diag(np.diag(H) + 1e-12), -g)
            Rn, tn = _exp_so3(step[:3]) @ R, t + step[3:]
            en = resid(Rn, tn)
            cn = float(np.sum(en * en))
            if cn <= cost:
                improved = cost - cn > 1e-15 * max(cost, 1e-300)
                R, t, e, cost = Rn, tn, en, cn
                mu = max(mu / 3.0, 1e-9)
                break
            mu *= 4.0
        if not improved or np.linalg.norm(step) < 1e-13:
            break
    return R, t


def _source_d2(pb: _Problem, R: np.ndarray, t: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per probe: sum over arrays of eq. (17)'s squared Mahalanobis distances at the fused position, and its
    degrees of freedom ``3 (n_obs - 1)``."""
    e = _residuals(pb, R, t, X)
    d2 = np.sum(e * e, axis=(0, 2))
    dof = 3 * (pb.valid.sum(0) - 1)
    return np.where(np.all(np.isfinite(X), 1), d2, np.nan), dof


def _robust_variance_factor(d2: np.ndarray, dof: np.ndarray, use: np.ndarray) -> float:
    """Median-based variance factor: ``median(d2 / median(chi2_dof))`` over ``use`` (>= a tiny floor)."""
    u = use & np.isfinite(d2) & (dof > 0)
    if not np.any(u):
        return 1.0
    z = d2[u] / scipy.stats.chi2.median(dof[u])
    # floor: on (near) noiseless data every d2 is rounding noise and none should count as an outlier
    return float(max(np.median(z), _MIN_VARIANCE_FACTOR))


def _robust_weights(pb: _Problem, R, t, X, active: np.ndarray, robust: bool) -> np.ndarray:
    """Per-probe weights: 1 on ``active`` probes, or Cauchy IRLS weights ``1 / (1 + d2 / c2)`` with
    ``c2 = v chi2_dof(0.95)`` (``v``: robust variance factor) when ``robust``."""
    if not robust:
        return active.astype(float)
    d2, dof = _source_d2(pb, R, t, X)
    v = _robust_variance_factor(d2, dof, active)
    c2 = v * scipy.stats.chi2.ppf(_CAUCHY_QUANTILE, np.maximum(dof, 1))
    return np.where(active & np.isfinite(d2), 1.0 / (1.0 + np.nan_to_num(d2) / c2), 0.0)


def _normal_equations(pb: _Problem, R: np.ndarray, t: np.ndarray, X: np.ndarray, w: np.ndarray):
    """Gauss-Newton blocks of ``sum_s w_s sum_k |e_ks|^2``, ``e_ks = W_ks (x_ks - R_k^T (X_s - t_k))``.

    Pose parameters (all arrays but the reference, 6 each): rotation increment ``R_k <- Exp(delta) R_k``
    (radians about the reference axes) and translation (m); the derivatives are exact at ``delta = 0``:
    ``de/ddelta = -W R^T [X - t]_x``, ``de/dt = W R^T``, ``de/dX = -W R^T``.

    Returns ``Hpp (P, P)``, ``Hxx (S, 3, 3)``, ``Hpx (S, P, 3)``, ``gp (P,)``, ``gx (S, 3)`` with ``P = 6 (K - 1)``;
    probes with ``w = 0`` or a NaN fused position contribute nothing.
    """
    K, S = pb.valid.shape
    poses = [k for k in range(K) if k != pb.reference]
    n_p = 6 * len(poses)
    Hpp, gp = np.zeros((n_p, n_p)), np.zeros(n_p)
    Hxx, Hpx, gx = np.zeros((S, 3, 3)), np.zeros((S, n_p, 3)), np.zeros((S, 3))
    use = (w > 0) & np.all(np.isfinite(X), 1)
    e_all = _residuals(pb, R, t, X)
    for k in range(K):
        m = pb.valid[k] & use
        if not np.any(m):
            continue
        sw = np.sqrt(w[m])[:, None, None]
        WRt = np.einsum("sij,kj->sik", pb.W[k, m], R[k]) * sw  # W R^T
        e = e_all[k, m] * sw[..., 0]
        Jx = -WRt
        Hxx[m] += np.einsum("sji,sjk->sik", Jx, Jx)
        gx[m] += np.einsum("sji,sj->si", Jx, e)
        if k == pb.reference:
            continue
        Jp = np.concatenate([-np.einsum("sij,sjk->sik", WRt, _skew(X[m] - t[k])), WRt], axis=2)  # (s, 3, 6)
        i = 6 * poses.index(k)
        Hpp[i:i + 6, i:i + 6] += np.einsum("sji,sjk->ik", Jp, Jp)
        gp[i:i + 6] += np.einsum("sji,sj->i", Jp, e)
        Hpx[m, i:i + 6, :] += np.einsum("sji,sjk->sik", Jp, Jx)
    return Hpp, Hxx, Hpx, gp, gx


def _reduced_system(Hpp, Hxx, Hpx, gp, gx):
    """Eliminate the probe positions (Schur complement): ``H = Hpp - sum Hpx Hxx^-1 Hxp``,
    ``g = gp - sum Hpx Hxx^-1 gx``."""
    ok = np.linalg.det(Hxx) > 0
    H, g = Hpp.copy(), gp.copy()
    if np.any(ok):
        Hinv = np.linalg.inv(Hxx[ok])
        H -= np.einsum("sij,sjk,slk->il", Hpx[ok], Hinv, Hpx[ok])
        g -= np.einsum("sij,sjk,sk->i", Hpx[ok], Hinv, gx[ok])
    return 0.5 * (H + H.T), g


def _apply_step(pb: _Problem, R: np.ndarray, t: np.ndarray, step: np.ndarray):
    R, t = R.copy(), t.copy()
    i = 0
    for k in range(R.shape[0]):
        if k == pb.reference:
            continue
        R[k] = _exp_so3(step[i:i + 3]) @ R[k]
        t[k] = t[k] + step[i + 3:i + 6]
        i += 6
    return R, t


def _weighted_cost(pb: _Problem, R, t, X, w) -> float:
    e = _residuals(pb, R, t, X)
    return float(np.sum(w * np.nan_to_num(np.sum(e * e, axis=(0, 2)))))


def _alternate(pb: _Problem, R: np.ndarray, t: np.ndarray, active: np.ndarray, *, robust_weights: bool,
               max_iterations: int, tolerance_rad: float, tolerance_m: float, pose_step: PoseStep):
    """Steps 1-2 alternated until every pose moves by less than the tolerances.

    Step 1 is eq. (15) (:func:`_fuse`). Step 2 with ``pose_step="paper"``: each pose by nonlinear least squares
    with the fused probes held fixed (:func:`_fit_pose`), as the paper; this block-coordinate descent crawls
    along the weakly determined directions of far-field geometry (hundreds to thousands of alternations).
    With ``pose_step="schur"``: one damped Gauss-Newton (Levenberg-Marquardt) step on all poses whose normal
    equations include the response of the fused probes (probe positions eliminated by the Schur complement),
    then step 1 again; the same fixed point (the maximum of the likelihood (9) over poses and probes),
    reached in about ten alternations. Returns ``R, t, X, iterations, converged``.
    """
    R, t = R.copy(), t.copy()
    K = R.shape[0]
    X = _fuse(pb, R, t, active)
    mu = 1e-4
    for it in range(1, max_iterations + 1):
        w = _robust_weights(pb, R, t, X, active, robust_weights)
        if pose_step == "paper":
            move_rad, move_m = 0.0, 0.0
            for k in range(K):
                if k == pb.reference:
                    continue
                Rk, tk = _fit_pose(pb, k, R[k], t[k], X, w)  # step 2
                move_rad = max(move_rad, float(np.linalg.norm(Rotation.from_matrix(Rk @ R[k].T).as_rotvec())))
                move_m = max(move_m, float(np.linalg.norm(tk - t[k])))
                R[k], t[k] = Rk, tk
            X = _fuse(pb, R, t, active)  # step 1 (eq. 15)
            if move_rad < tolerance_rad and move_m < tolerance_m:
                return R, t, X, it, True
            continue
        H, g = _reduced_system(*_normal_equations(pb, R, t, X, w))
        cost = _weighted_cost(pb, R, t, X, w)
        accepted = False
        for _ in range(16):
            try:
                step = np.linalg.solve(H + mu * np.diag(np.diag(H) + 1e-12 * np.trace(H)), -g)
            except np.linalg.LinAlgError:
                mu *= 10.0
                continue
            Rn, tn = _apply_step(pb, R, t, step)
            Xn = _fuse(pb, Rn, tn, active)  # step 1 (eq. 15)
            cn = _weighted_cost(pb, Rn, tn, Xn, w)
            if cn <= cost:
                R, t, X, accepted = Rn, tn, Xn, True
                mu = max(mu / 5.0, 1e-12)
                break
            mu *= 5.0
        if not accepted:  # no descent direction left: at the minimum to numerical precision
            return R, t, X, it, True
        s = step.reshape(-1, 6)
        if np.max(np.linalg.norm(s[:, :3], axis=1)) < tolerance_rad and \
                np.max(np.linalg.norm(s[:, 3:], axis=1)) < tolerance_m:
            return R, t, X, it, True
    return R, t, X, max_iterations, False


def _pose_information(pb: _Problem, R: np.ndarray, t: np.ndarray, X: np.ndarray, use: np.ndarray) -> np.ndarray:
    """Gauss-Newton information of all non-reference poses with the probe positions eliminated (Schur
    complement). Parameters per pose: rotation increment about the reference axes (rad), translation (m)."""
    H, _ = _reduced_system(*_normal_equations(pb, R, t, X, use.astype(float)))
    return H


def _finish(pb: _Problem, R: np.ndarray, t: np.ndarray, X: np.ndarray, use: np.ndarray, *, method: Method,
            rejected, n_iterations: int, converged: bool, max_rotation_std_deg: float | None,
            max_variance_factor: float | None = None) -> MultiArrayCalibration:
    K = R.shape[0]
    d2, dof = _source_d2(pb, R, t, X)
    u = use & np.isfinite(d2)
    n_params = 6 * (K - 1)
    dof_total = int(np.sum(dof[u])) - n_params
    cost = float(np.sum(d2[u]))
    v = cost / dof_total if dof_total > 0 else float("nan")
    if max_variance_factor is not None and v > max_variance_factor:
        raise InconsistentDataError(
            f"the probe localisations disagree far beyond their stated uncertainty (variance factor {v:.3g} > "
            f"{max_variance_factor=}): unreliable TDOAs (low SNR, reverberation) or sigma_tdoa_s far too small")
    info = _pose_information(pb, R, t, X, u)
    lam, V = np.linalg.eigh(info)
    # A null direction of the information is a pose the probes do not determine.
    lam_ok = lam > 1e-12 * max(lam[-1], 1e-300)
    cov = (V / np.where(lam_ok, lam, np.inf)) @ V.T * (v if np.isfinite(v) and v > 0 else 1.0)
    poses, i = [], 0
    for k in range(K):
        if k == pb.reference:
            poses.append(ArrayPose.identity())
            continue
        c = cov[i:i + 6, i:i + 6] if np.all(lam_ok) else np.full((6, 6), np.inf)  # singular: undetermined
        rot_std = np.degrees(np.sqrt(np.maximum(np.diag(c)[:3], 0)))
        poses.append(ArrayPose(R[k], t[k], rot_std, np.sqrt(np.maximum(np.diag(c)[3:], 0)), c))
        if max_rotation_std_deg is not None and np.max(rot_std) > max_rotation_std_deg:
            raise UnobservablePoseError(
                f"the probes do not determine the pose of array {k}: rotation std {np.max(rot_std):.3g} deg > "
                f"{max_rotation_std_deg=} (probes nearly collinear or bunched in one direction, too few or too "
                "noisy)")
        i += 6
    return MultiArrayCalibration(tuple(poses), pb.reference, method, X, tuple(rejected), v, cost, n_iterations,
                                 converged)


def refine_mle(source_positions_m: Sequence, covariances_m2: Sequence, initial_poses: Sequence[ArrayPose], *,
               reference_array: int = 0, robust: bool = True, reject_quantile: float = 0.999,
               max_iterations: int = 200, tolerance_deg: float = 1e-5, tolerance_m: float = 1e-6,
               max_rotation_std_deg: float | None = 30.0, max_variance_factor: float | None = 100.0,
               pose_step: PoseStep = "schur") -> MultiArrayCalibration:
    """Maximum-likelihood poses from localisations with anisotropic covariances (paper Sec. III-B).

    Alternates step 1 (eq. 15: fuse each probe over the arrays given the poses) and step 2 (eq. 17: each
    array's pose by nonlinear least squares on the whitened residuals, fused probes fixed) from
    ``initial_poses`` until every pose moves by less than ``tolerance_deg`` and ``tolerance_m``. The
    covariances stay fixed (the paper's ``Sigma ~ Sigma_bar(X_hat)``). See the module docstring for the
    robust phase and the rejection. No degeneracy pre-checks here (:func:`calibrate_from_locations` makes
    them); only the rotation std limit after the solve.

    Parameters
    ----------
    source_positions_m : sequence of ndarray, shape (n_sources, 3), float
        Per array, the probes localised in its own frame, metres; NaN rows are missing localisations.
    covariances_m2 : sequence of ndarray, shape (n_sources, 3, 3), float
        Per array, the covariance of each localisation in its own frame, square metres.
    initial_poses : sequence of ArrayPose
        One per array (the reference's is ignored).
    reference_array : int
    robust : bool
        Cauchy-weighted phase, rejection of probes above ``reject_quantile`` and a re-solve.
    reject_quantile : float
        Chi-square quantile of the fused distance (scaled by the robust variance factor) above which a probe
        is rejected.
    max_iterations : int
        Alternations per round.
    tolerance_deg, tolerance_m : float
        Convergence: largest pose change per alternation, degrees and metres.
    max_rotation_std_deg : float or None
        Raise :class:`UnobservablePoseError` above this rotation std (None: never).
    max_variance_factor : float or None
        Raise :class:`InconsistentDataError` when the a-posteriori variance factor of the kept probes exceeds
        this (default 100: errors ten times the stated ones; a wrong solution on unreliable TDOAs measured
        800-1800 where a right one on the same data gave 10-20). None: never.
    pose_step : {"schur", "paper"}
        Step 2 as a joint Gauss-Newton step with the fused probes' response eliminated (default; about ten
        alternations), or as the paper's fit with the fused probes fixed (same optimum, far slower in the far
        field: raise ``max_iterations``). See :func:`_alternate`.

    Returns
    -------
    MultiArrayCalibration
    """
    K = len(source_positions_m)
    if K < 2 or len(covariances_m2) != K or len(initial_poses) != K:
        raise ValueError(f"need >= 2 arrays with one localisation set, covariance set and initial pose each; got "
                         f"{K}, {len(covariances_m2)}, {len(initial_poses)}")
    if not 0 <= reference_array < K:
        raise ValueError(f"{reference_array=} must be in 0..{K - 1}")
    if not 0.5 < reject_quantile < 1:
        raise ValueError(f"{reject_quantile=} must be in (0.5, 1)")
    if max_iterations < 1:
        raise ValueError(f"{max_iterations=} must be >= 1")
    n = np.shape(source_positions_m[0])[0]
    for k in range(K):
        if np.shape(source_positions_m[k]) != (n, 3) or np.shape(covariances_m2[k]) != (n, 3, 3):
            raise ValueError(f"array {k}: localisations {np.shape(source_positions_m[k])} and covariances "
                             f"{np.shape(covariances_m2[k])} must be ({n}, 3) m and ({n}, 3, 3) m^2")
    pb = _Problem.build(source_positions_m, covariances_m2, reference_array)
    R = np.stack([p.rotation_matrix for p in initial_poses]).copy()
    t = np.stack([p.translation_m for p in initial_poses]).copy()
    R[reference_array], t[reference_array] = np.eye(3), np.zeros(3)
    if pose_step not in ("schur", "paper"):
        raise ValueError(f"{pose_step=} must be 'schur' or 'paper'")
    kw = dict(max_iterations=max_iterations, tolerance_rad=np.radians(tolerance_deg), tolerance_m=tolerance_m,
              pose_step=pose_step)
    active = pb.valid.sum(0) >= 2
    if int(np.count_nonzero(active)) < MIN_SOURCES:
        raise TooFewSourcesError(f"only {int(np.count_nonzero(active))} probes are localised by two or more "
                                 f"arrays; calibration needs >= {MIN_SOURCES}")
    total_it, converged = 0, False
    if not robust:
        R, t, X, total_it, converged = _alternate(pb, R, t, active, robust_weights=False, **kw)
        return _finish(pb, R, t, X, active, method="mle", rejected=(), n_iterations=total_it, converged=converged,
                       max_rotation_std_deg=max_rotation_std_deg, max_variance_factor=max_variance_factor)
    R, t, X, it, converged = _alternate(pb, R, t, active, robust_weights=True, **kw)
    total_it += it
    keep = active.copy()
    for round_ in range(5):
        X_all = _fuse(pb, R, t, active)  # every probe, also the rejected ones
        d2, dof = _source_d2(pb, R, t, X_all)
        v = _robust_variance_factor(d2, dof, active)  # over all probes: a trimmed set would cascade
        new_keep = active & np.isfinite(d2) & (d2 <= v * scipy.stats.chi2.ppf(reject_quantile, np.maximum(dof, 1)))
        if np.count_nonzero(new_keep) < MIN_SOURCES:
            new_keep = keep
        if round_ > 0 and np.array_equal(new_keep, keep):
            break
        keep = new_keep
        R, t, X, it, converged = _alternate(pb, R, t, keep, robust_weights=False, **kw)
        total_it += it
    X = _fuse(pb, R, t, keep)
    rejected = np.flatnonzero(active & ~keep)
    if rejected.size:
        log.debug("refine_mle rejected probes %s", rejected.tolist())
    return _finish(pb, R, t, X, keep, method="mle", rejected=rejected, n_iterations=total_it, converged=converged,
                   max_rotation_std_deg=max_rotation_std_deg, max_variance_factor=max_variance_factor)


def calibrate_from_locations(source_positions_m: Sequence, covariances_m2: Sequence | None = None, *,
                             method: Method = "mle", reference_array: int = 0,
                             rng: np.random.Generator | int = 0, robust: bool = True,
                             ransac_hypotheses: int = 256, ransac_threshold_m: float | None = None,
                             min_spread_deg: float = 2.0, max_rotation_std_deg: float | None = 30.0,
                             max_variance_factor: float | None = 100.0, max_iterations: int = 200,
                             pose_step: PoseStep = "schur") -> MultiArrayCalibration:
    """Poses of ``K >= 2`` arrays from the probe localisations each one made in its own frame.

    ``method="rigid_body"``: RANSAC + Kabsch of every array against the reference (:func:`rigid_body_ransac`),
    the paper's [6]. ``method="mle"``: that, then the MLE of every array against the reference
    (:func:`refine_mle` on the pair), then, with ``K > 2``, a joint MLE refinement of all poses.

    Parameters
    ----------
    source_positions_m : sequence of ndarray, shape (n_sources, 3), float
        One per array, probe ``s`` in row ``s`` of every array; NaN rows are missed probes.
    covariances_m2 : sequence of ndarray, shape (n_sources, 3, 3), float, or None
        Localisation covariances (square metres, local frames); required for ``"mle"``; with
        ``"rigid_body"`` only used to refuse far-field probe sets coplanar with both arrays.
    method : {"mle", "rigid_body"}
    reference_array : int
    rng : numpy.random.Generator or int
        RANSAC samples.
    robust : bool
        See :func:`refine_mle`.
    ransac_hypotheses : int
    ransac_threshold_m : float or None
        See :func:`rigid_body_ransac` (None: least median of squares).
    min_spread_deg : float
        Smallest accepted angular spread of the probes around their mean direction, seen from each array's
        local origin, degrees.
    max_rotation_std_deg : float or None
        See :func:`refine_mle` (also applied to ``"rigid_body"``).
    max_variance_factor : float or None
        See :func:`refine_mle` (``"mle"`` only).
    max_iterations, pose_step
        See :func:`refine_mle`.

    Returns
    -------
    MultiArrayCalibration

    Raises
    ------
    TooFewSourcesError, DegenerateSourcesError, UnobservablePoseError, InconsistentDataError
    """
    K = len(source_positions_m)
    if K < 2:
        raise ValueError(f"need >= 2 arrays; got {K}")
    if not 0 <= reference_array < K:
        raise ValueError(f"{reference_array=} must be in 0..{K - 1}")
    if method not in ("mle", "rigid_body"):
        raise ValueError(f"{method=} must be 'mle' or 'rigid_body'")
    pts = [np.asarray(p, float) for p in source_positions_m]
    n = pts[0].shape[0] if pts[0].ndim == 2 else -1
    for k, p in enumerate(pts):
        if p.ndim != 2 or p.shape != (n, 3):
            raise ValueError(f"source_positions_m[{k}] has shape {p.shape}; expected ({n}, 3) metres, the same "
                             "probes in the same rows for every array")
    covs = None
    if method == "mle" and covariances_m2 is None:
        raise ValueError("method='mle' needs one (n_sources, 3, 3) covariance array per array")
    if covariances_m2 is not None:
        if len(covariances_m2) != K:
            raise ValueError(f"{len(covariances_m2)} covariance arrays for {K} arrays; need one per array")
        covs = [np.asarray(c, float) for c in covariances_m2]
        for k, c in enumerate(covs):
            if c.shape != (n, 3, 3):
                raise ValueError(f"covariances_m2[{k}] has shape {c.shape}; expected ({n}, 3, 3) square metres")
    rng = np.random.default_rng(rng)
    ref = pts[reference_array]
    init = [ArrayPose.identity() for _ in range(K)]
    rbm_inliers = np.ones(n, bool)
    for k in range(K):
        if k == reference_array:
            continue
        _check_pair(ref, pts[k], k, reference_array, min_spread_deg, *(
            (covs[reference_array], covs[k]) if covs is not None else (None, None)))
        init[k], inl = rigid_body_ransac(ref, pts[k], rng=rng, n_hypotheses=ransac_hypotheses,
                                         threshold_m=ransac_threshold_m)
        both = np.all(np.isfinite(ref), 1) & np.all(np.isfinite(pts[k]), 1)
        rbm_inliers &= inl | ~both
    if method == "rigid_body":
        ones = np.broadcast_to(np.eye(3), (n, 3, 3))
        pb = _Problem.build(pts, [ones] * K, reference_array)
        R = np.stack([p.rotation_matrix for p in init])
        t = np.stack([p.translation_m for p in init])
        use = rbm_inliers & (pb.valid.sum(0) >= 2)
        X = _fuse(pb, R, t, use)
        return _finish(pb, R, t, X, use, method="rigid_body", rejected=np.flatnonzero(~rbm_inliers),
                       n_iterations=0, converged=True, max_rotation_std_deg=max_rotation_std_deg)
    kw = dict(robust=robust, max_iterations=max_iterations, max_rotation_std_deg=max_rotation_std_deg,
              max_variance_factor=max_variance_factor, pose_step=pose_step)
    if K == 2:
        return refine_mle(pts, covs, init, reference_array=reference_array, **kw)
    pair_poses = list(init)
    for k in range(K):
        if k != reference_array:
            pair = refine_mle([ref, pts[k]], [covs[reference_array], covs[k]], [init[reference_array], init[k]],
                              reference_array=0, **kw)
            pair_poses[k] = pair.poses[1]
    return refine_mle(pts, covs, pair_poses, reference_array=reference_array, **kw)


def calibrate_arrays(tdoa_s: Sequence, mic_positions_m: Sequence, *, sigma_tdoa_s: float | Sequence[float],
                     speed_of_sound_m_s: float = SPEED_OF_SOUND_M_S, reference_mics: int | Sequence[int] = 0,
                     method: Method = "mle", reference_array: int = 0, rng: np.random.Generator | int = 0,
                     reject_tdoa_outliers: bool = True, **options) -> MultiArrayCalibration:
    """Poses of ``K >= 2`` arrays from each array's TDOAs of the same probes (the paper's whole method).

    Every array localises the probes by spherical least squares (:func:`localize_spherical_ls`), the CRLB
    covariance is evaluated at each estimate (:func:`localization_covariance`), and
    :func:`calibrate_from_locations` finds the poses.

    Parameters
    ----------
    tdoa_s : sequence of ndarray, shape (n_sources, n_mics_k), float
        Per array ``k``: ``toa[m] - toa[reference_mic]`` of each probe, seconds (NaN: not measured).
    mic_positions_m : sequence of ndarray, shape (n_mics_k, 3), float
        Per array, its mic positions in its own frame, metres.
    sigma_tdoa_s : float or sequence of float
        TDOA noise std per array (or one for all), seconds.
    speed_of_sound_m_s : float
    reference_mics : int or sequence of int
        TDOA reference mic per array.
    method : {"mle", "rigid_body"}
    reference_array : int
    rng : numpy.random.Generator or int
    reject_tdoa_outliers : bool
        Drop inconsistent TDOAs (wrong GCC peaks) in the localisation (see :func:`localize_spherical_ls`).
    **options
        Passed to :func:`calibrate_from_locations` (``robust``, ``ransac_threshold_m``, ``min_spread_deg``, ...).

    Returns
    -------
    MultiArrayCalibration
        ``sigma_tdoa_s`` (the first array's if several) and ``speed_of_sound_m_s`` recorded.

    Raises
    ------
    DegenerateArrayError, TooFewSourcesError, DegenerateSourcesError, UnobservablePoseError,
    InconsistentDataError
    """
    K = len(tdoa_s)
    if len(mic_positions_m) != K:
        raise ValueError(f"{len(tdoa_s)} TDOA sets but {len(mic_positions_m)} mic geometries; need one per array")
    sig = np.broadcast_to(np.asarray(sigma_tdoa_s, float), (K,))
    refs = np.broadcast_to(np.asarray(reference_mics, int), (K,))
    pts, covs = [], []
    for k in range(K):
        mics = _check_mics(mic_positions_m[k], int(refs[k]), name=f"array {k}")
        x, used = localize_spherical_ls(np.atleast_2d(tdoa_s[k]), mics, speed_of_sound_m_s=speed_of_sound_m_s,
                                        reference_mic=int(refs[k]), reject_outliers=reject_tdoa_outliers,
                                        return_inliers=True)
        pts.append(x)
        covs.append(localization_covariance(x, mics, sigma_tdoa_s=float(sig[k]), tdoa_used=used,
                                            speed_of_sound_m_s=speed_of_sound_m_s, reference_mic=int(refs[k])))
    res = calibrate_from_locations(pts, covs, method=method,
                                   reference_array=reference_array, rng=rng, **options)
    return dataclasses.replace(res, sigma_tdoa_s=float(sig[0]), speed_of_sound_m_s=float(speed_of_sound_m_s))


# ------------------------------------------------------------------------------------------ the paper's setup
def paper_array_m(spacing_m: float = 0.35, plane_offset_m: float = 0.2) -> np.ndarray:
    """The paper's 18-mic array (Fig. 4): two parallel 3 x 3 grids of ``spacing_m``, ``plane_offset_m`` apart,
    looking along +x; shape (18, 3) m, row 0 (the reference mic) at the local origin."""
    g = spacing_m * np.array([-1.0, 0.0, 1.0])
    yy, zz = np.meshgrid(g, g, indexing="ij")
    front = np.stack([np.zeros(9), yy.ravel(), zz.ravel()], 1)
    mics = np.concatenate([front, front - [plane_offset_m, 0.0, 0.0]])
    ref = int(np.argmin(np.sum(mics**2, 1)))
    return mics[[ref] + [i for i in range(len(mics)) if i != ref]]


def paper_scene(d_m: float, yaw_deg: float, n_sources: int, rng: np.random.Generator) -> tuple[ArrayPose, np.ndarray]:
    """The paper's experiments: array 1 at the origin, ``n_sources`` probes around ``[d, 0, 0]``, array 2 at
    distance ``d`` from them, turned by ``yaw_deg`` and looking at them. Returns array 2's true pose and the
    probe positions in array 1's frame (metres)."""
    centre = np.array([d_m, 0.0, 0.0])
    y = np.radians(yaw_deg)
    pose = ArrayPose.from_deg([0.0, 0.0, yaw_deg], centre - d_m * np.array([np.cos(y), np.sin(y), 0.0]))
    half = np.array([min(1.0, d_m / 2), min(1.0, d_m / 2), 0.5])
    return pose, centre + rng.uniform(-1.0, 1.0, (n_sources, 3)) * half

