"""Lie-group (SO(3), SE(3)) math on numpy arrays; pinhole projection is in :mod:`.projection`.

Every function is vectorised over leading batch dimensions written ``...``; batch dimensions
of several arguments broadcast against each other like numpy's. Inputs are converted to
float64. Shapes are validated at the boundary and a wrong shape raises ``ValueError``.

Conventions (see ``docs/conventions.md``):

- ``T_a_b`` (4, 4) is the pose of frame b in frame a; it maps points in b into a, so
  composition cancels the inner name: ``T_cam_obj = compose(invert(T_world_cam), T_world_obj)``.
- Units are metres and radians.
- Rotation vectors ``w`` (3,) are axis * angle; ``hat(w) @ v == cross(w, v)``.
- SO(3) Jacobians: ``exp(w + dw) ~= exp(J_l(w) dw) exp(w) ~= exp(w) exp(J_r(w) dw)``, and
  ``J_r(w) == J_l(-w)``.
- se(3) tangent vectors are ``xi = [rho, phi]``: translation part first (3), rotation part
  second (3), the same order as the project's 6x6 covariances (x, y, z, rot_x, rot_y, rot_z).

The exponential, logarithm and Jacobians are explicit numpy with small-angle Taylor branches
(and, for the logarithm, a near-pi branch) so that they are accurate to machine precision at
every angle in [0, pi].
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = [
    "compose",
    "hat",
    "invert",
    "is_rotation",
    "make_transform",
    "random_rotations",
    "rotation_angle",
    "se3_exp",
    "se3_log",
    "so3_exp",
    "so3_left_jacobian",
    "so3_left_jacobian_inv",
    "so3_log",
    "so3_right_jacobian",
    "so3_right_jacobian_inv",
    "transform_points",
    "vee",
]

# Below this angle the Taylor series are used; their truncation error at the threshold is
# below 1e-20 relative, and the closed forms are well conditioned above it.
_SMALL_ANGLE = 1e-2
# so3_log recovers the axis from the symmetric part of R when cos(angle) is below this value
# (angle above 2*pi/3), where sin(angle) is too small to divide the skew part by.
_NEAR_PI_COS = -0.5


# --------------------------------------------------------------------------- validation
def _as_array(x: object, trailing: tuple[int, ...], name: str) -> np.ndarray:
    """``x`` as a float64 array whose last dimensions are ``trailing``."""
    arr = np.asarray(x, dtype=np.float64)
    k = len(trailing)
    if arr.ndim < k or arr.shape[arr.ndim - k :] != trailing:
        want = ", ".join(["..."] + [str(d) for d in trailing])
        raise ValueError(f"{name} must have shape ({want}), got {arr.shape}")
    return arr


_IDENTITY = np.eye(3)
_IDENTITY.setflags(write=False)


def _mv(M: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Batched matrix-vector product: (...,m,n),(...,n) -> (...,m)."""
    return np.matmul(M, v[..., None])[..., 0]


def _series(theta2: np.ndarray, coeffs: tuple[float, ...]) -> np.ndarray:
    """sum_k coeffs[k] * theta2**k by Horner's rule."""
    out = np.full_like(theta2, coeffs[-1])
    for c in reversed(coeffs[:-1]):
        out = out * theta2 + c
    return out


def _small_or(
    small: np.ndarray, t2: np.ndarray, coeffs: tuple[float, ...], direct: np.ndarray
) -> np.ndarray:
    """``np.where(small, _series(t2, coeffs), direct)``, the series summed only where some
    angle is small (the estimator's batches seldom have one: a third of their time saved)."""
    if not small.any():
        return direct
    return np.where(small, _series(t2, coeffs), direct)


def _split_small(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(small mask, theta with small entries replaced by 1, theta**2)."""
    small = theta < _SMALL_ANGLE
    safe = np.where(small, 1.0, theta)
    return small, safe, theta * theta


# Taylor coefficients in powers of theta**2.
_A_SERIES = (1.0, -1.0 / 6, 1.0 / 120, -1.0 / 5040, 1.0 / 362880)  # sin(t)/t
_B_SERIES = (0.5, -1.0 / 24, 1.0 / 720, -1.0 / 40320, 1.0 / 3628800)  # (1-cos t)/t^2
_C_SERIES = (1.0 / 6, -1.0 / 120, 1.0 / 5040, -1.0 / 362880, 1.0 / 39916800)  # (t-sin t)/t^3
# (1 - (t/2) cot(t/2)) / t^2
_D_SERIES = (1.0 / 12, 1.0 / 720, 1.0 / 30240, 1.0 / 1209600, 1.0 / 47900160)
# t / sin(t)
_INV_A_SERIES = (1.0, 1.0 / 6, 7.0 / 360, 31.0 / 15120, 127.0 / 604800)


def _coef_a(theta: np.ndarray) -> np.ndarray:
    """sin(theta) / theta."""
    small, safe, t2 = _split_small(theta)
    return _small_or(small, t2, _A_SERIES, np.sin(safe) / safe)


def _coef_b(theta: np.ndarray) -> np.ndarray:
    """(1 - cos(theta)) / theta**2, computed as 2 sin^2(theta/2) / theta**2."""
    small, safe, t2 = _split_small(theta)
    direct = 0.5 * (np.sin(0.5 * safe) / (0.5 * safe)) ** 2
    return _small_or(small, t2, _B_SERIES, direct)


def _coef_c(theta: np.ndarray) -> np.ndarray:
    """(theta - sin(theta)) / theta**3."""
    small, safe, t2 = _split_small(theta)
    return _small_or(small, t2, _C_SERIES, (safe - np.sin(safe)) / safe**3)


def _coef_d(theta: np.ndarray) -> np.ndarray:
    """(1 - (theta/2) cot(theta/2)) / theta**2; finite on [0, 2*pi)."""
    small, safe, t2 = _split_small(theta)
    half = 0.5 * safe
    direct = (1.0 - half * np.cos(half) / np.sin(half)) / (safe * safe)
    return _small_or(small, t2, _D_SERIES, direct)


# --------------------------------------------------------------------------- so(3)
_VEE_ROWS = np.array([2, 0, 1])  # vee(W) = (W[2,1] - W[1,2], W[0,2] - W[2,0], W[1,0] - W[0,1]) / 2
_VEE_COLS = np.array([1, 2, 0])


def hat(w: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix of a 3-vector, so that ``hat(w) @ v == np.cross(w, v)``.

    Args:
        w: (..., 3).

    Returns:
        (..., 3, 3).
    """
    w = _as_array(w, (3,), "hat: w")
    W = np.zeros(w.shape[:-1] + (3, 3))
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    W[..., 0, 1] = -z
    W[..., 0, 2] = y
    W[..., 1, 0] = z
    W[..., 1, 2] = -x
    W[..., 2, 0] = -y
    W[..., 2, 1] = x
    return W


def vee(W: np.ndarray) -> np.ndarray:
    """Inverse of :func:`hat`: the 3-vector of the skew-symmetric part of ``W``.

    For a non-skew ``W`` this returns ``vee((W - W^T) / 2)``.

    Args:
        W: (..., 3, 3).

    Returns:
        (..., 3).
    """
    W = _as_array(W, (3, 3), "vee: W")
    return 0.5 * (W[..., _VEE_ROWS, _VEE_COLS] - W[..., _VEE_COLS, _VEE_ROWS])


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues' formula).

    ``R = I + A hat(w) + B hat(w)^2`` with ``A = sin(t)/t``, ``B = (1 - cos(t))/t^2``,
    ``t = |w|``; Taylor series below 1e-2 rad, so tiny angles are exact to machine precision.

    Args:
        w: (..., 3) rotation vector (axis * angle), radians.

    Returns:
        (..., 3, 3) rotation matrix.
    """
    w = _as_array(w, (3,), "so3_exp: w")
    if w.ndim == 1:  # one vector, the common case in the estimator's loops: scalar maths
        return _so3_exp_one(w)
    theta = np.linalg.norm(w, axis=-1)
    W = hat(w)
    A = _coef_a(theta)[..., None, None]
    B = _coef_b(theta)[..., None, None]
    return _IDENTITY + A * W + B * (W @ W)


def _so3_exp_one(w: np.ndarray) -> np.ndarray:
    """:func:`so3_exp` of one (3,) vector, the coefficients in Python floats (a tenth of the
    batched path's time for a single rotation; equal to rounding)."""
    x, y, z = float(w[0]), float(w[1]), float(w[2])
    t2 = x * x + y * y + z * z
    t = math.sqrt(t2)
    if t < _SMALL_ANGLE:
        A = _series_scalar(t2, _A_SERIES)
        B = _series_scalar(t2, _B_SERIES)
    else:
        A = math.sin(t) / t
        B = 0.5 * (math.sin(0.5 * t) / (0.5 * t)) ** 2
    W = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return _IDENTITY + A * W + B * (W @ W)


def _series_scalar(theta2: float, coeffs: tuple[float, ...]) -> float:
    out = coeffs[-1]
    for c in reversed(coeffs[:-1]):
        out = out * theta2 + c
    return out


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix, the inverse of :func:`so3_exp`.

    The angle ``t = atan2(|s|, (tr R - 1)/2)`` with ``s = vee(R - R^T)/2 = sin(t) * axis`` lies
    in [0, pi] and is accurate everywhere. For ``t`` up to 2*pi/3 the result is
    ``s * t / sin(t)`` (Taylor series near 0). Above, the axis comes from the symmetric part
    ``(R + R^T)/2 - cos(t) I = (1 - cos(t)) axis axis^T`` (its largest column, normalised),
    with the sign that makes it agree with ``s``; at exactly pi, where ``s`` vanishes and both
    signs are valid, the sign making the largest-magnitude component positive is returned.

    ``R`` is assumed to be a rotation (see :func:`is_rotation`); it is not re-orthonormalised.

    Args:
        R: (..., 3, 3) rotation matrix.

    Returns:
        (..., 3) rotation vector with norm in [0, pi].
    """
    R = _as_array(R, (3, 3), "so3_log: R")
    if R.ndim == 2:  # one matrix, the common case in the estimator's loops: scalar maths
        w = _so3_log_one(R)
        if w is not None:
            return w
    s = vee(R)
    sin_t = np.linalg.norm(s, axis=-1)
    cos_t = np.clip(0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0), -1.0, 1.0)
    theta = np.arctan2(sin_t, cos_t)

    # Generic and small-angle branch: w = s * t / sin(t).
    small, safe, t2 = _split_small(theta)
    safe_sin = np.where(small, 1.0, np.sin(safe))
    t_over_sin = _small_or(small, t2, _INV_A_SERIES, safe / safe_sin)
    w_generic = s * t_over_sin[..., None]
    near_pi = (cos_t < _NEAR_PI_COS)[..., None]
    if not np.any(near_pi):
        return w_generic

    # Near-pi branch: axis from the symmetric part.
    sym = 0.5 * (R + np.swapaxes(R, -1, -2)) - cos_t[..., None, None] * np.eye(3)
    diag = np.diagonal(sym, axis1=-2, axis2=-1)
    k = np.argmax(diag, axis=-1)
    col = np.take_along_axis(sym, k[..., None, None], axis=-1)[..., 0]
    col_norm = np.linalg.norm(col, axis=-1, keepdims=True)
    axis = col / np.where(col_norm > 0.0, col_norm, 1.0)
    dot = np.sum(axis * s, axis=-1)
    largest = np.take_along_axis(axis, np.argmax(np.abs(axis), axis=-1)[..., None], axis=-1)[..., 0]
    sign = np.where(dot != 0.0, np.sign(dot), np.where(largest < 0.0, -1.0, 1.0))
    w_pi = axis * (sign * theta)[..., None]
    return np.where(near_pi, w_pi, w_generic)


def _so3_log_one(R: np.ndarray) -> np.ndarray | None:
    """:func:`so3_log` of one (3, 3) matrix below the near-pi branch, the coefficients in
    Python floats (equal to rounding); None near pi, left to the batched path."""
    x = 0.5 * (float(R[2, 1]) - float(R[1, 2]))
    y = 0.5 * (float(R[0, 2]) - float(R[2, 0]))
    z = 0.5 * (float(R[1, 0]) - float(R[0, 1]))
    cos_t = min(1.0, max(-1.0, 0.5 * (float(R[0, 0]) + float(R[1, 1]) + float(R[2, 2]) - 1.0)))
    if cos_t < _NEAR_PI_COS:
        return None
    theta = math.atan2(math.sqrt(x * x + y * y + z * z), cos_t)
    if theta < _SMALL_ANGLE:
        factor = _series_scalar(theta * theta, _INV_A_SERIES)
    else:
        factor = theta / math.sin(theta)
    return np.array([x * factor, y * factor, z * factor])


def so3_left_jacobian(w: np.ndarray) -> np.ndarray:
    """Left Jacobian of SO(3): ``exp(w + dw) ~= exp(J_l(w) dw) exp(w)``.

    ``J_l = I + B hat(w) + C hat(w)^2``, ``B = (1 - cos t)/t^2``, ``C = (t - sin t)/t^3``.
    It is also the V matrix of the SE(3) exponential.

    Args:
        w: (..., 3) rotation vector.

    Returns:
        (..., 3, 3).
    """
    w = _as_array(w, (3,), "so3_left_jacobian: w")
    return _jacobian(w, 1.0)


def so3_right_jacobian(w: np.ndarray) -> np.ndarray:
    """Right Jacobian of SO(3): ``exp(w + dw) ~= exp(w) exp(J_r(w) dw)``; ``J_r(w) = J_l(-w)``.

    Args:
        w: (..., 3) rotation vector.

    Returns:
        (..., 3, 3).
    """
    w = _as_array(w, (3,), "so3_right_jacobian: w")
    return _jacobian(w, -1.0)


def so3_left_jacobian_inv(w: np.ndarray) -> np.ndarray:
    """Inverse of :func:`so3_left_jacobian`.

    ``J_l^-1 = I - hat(w)/2 + D hat(w)^2``, ``D = (1 - (t/2) cot(t/2))/t^2``; finite for
    ``|w| < 2 pi``.

    Args:
        w: (..., 3) rotation vector.

    Returns:
        (..., 3, 3).
    """
    w = _as_array(w, (3,), "so3_left_jacobian_inv: w")
    return _jacobian_inv(w, 1.0)


def so3_right_jacobian_inv(w: np.ndarray) -> np.ndarray:
    """Inverse of :func:`so3_right_jacobian`: ``J_r^-1 = I + hat(w)/2 + D hat(w)^2``.

    Args:
        w: (..., 3) rotation vector.

    Returns:
        (..., 3, 3).
    """
    w = _as_array(w, (3,), "so3_right_jacobian_inv: w")
    return _jacobian_inv(w, -1.0)


def so3_jacobian_inv_gram(w: np.ndarray) -> np.ndarray:
    """``J^T J`` for ``J`` either inverse Jacobian, left or right (both give the same product),
    in closed form: ``I + k hat(w)^2`` with ``k = 2 D - 1/4 - D^2 t^2``.

    With ``J = I -+ hat(w)/2 + D hat(w)^2``, ``hat(w)`` commutes with ``hat(w)^2`` and
    ``hat(w)^4 = -t^2 hat(w)^2``, so the cross terms cancel. This is the Gauss-Newton normal
    matrix of a residual ``log(R_k R^T)`` per member, without forming each Jacobian.

    Args:
        w: (..., 3) rotation vector.

    Returns:
        (..., 3, 3) symmetric positive definite.
    """
    w = _as_array(w, (3,), "so3_jacobian_inv_gram: w")
    theta = np.linalg.norm(w, axis=-1)
    D = _coef_d(theta)
    k = (2.0 * D - 0.25 - D * D * theta * theta)[..., None, None]
    W2 = w[..., :, None] * w[..., None, :] - (theta * theta)[..., None, None] * _IDENTITY
    return _IDENTITY + k * W2


def _jacobian(w: np.ndarray, side: float) -> np.ndarray:
    theta = np.linalg.norm(w, axis=-1)
    W = hat(w)
    B = _coef_b(theta)[..., None, None]
    C = _coef_c(theta)[..., None, None]
    return _IDENTITY + side * B * W + C * (W @ W)


def _jacobian_inv(w: np.ndarray, side: float) -> np.ndarray:
    theta = np.linalg.norm(w, axis=-1)
    W = hat(w)
    D = _coef_d(theta)[..., None, None]
    return _IDENTITY - side * 0.5 * W + D * (W @ W)


# --------------------------------------------------------------------------- SE(3)
def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Homogeneous transform ``[[R, t], [0, 1]]``.

    Args:
        R: (..., 3, 3) rotation ``R_a_b``.
        t: (..., 3) translation ``t_a_b``, metres. Batch dimensions broadcast with ``R``'s.

    Returns:
        (..., 4, 4) ``T_a_b``.
    """
    R = _as_array(R, (3, 3), "make_transform: R")
    t = _as_array(t, (3,), "make_transform: t")
    try:
        batch = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    except ValueError:
        raise ValueError(
            f"make_transform: batch shapes of R {R.shape} and t {t.shape} do not broadcast"
        ) from None
    T = np.zeros(batch + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def compose(T_a_b: np.ndarray, T_b_c: np.ndarray) -> np.ndarray:
    """``T_a_c = T_a_b @ T_b_c`` (batched, broadcasting).

    Args:
        T_a_b: (..., 4, 4).
        T_b_c: (..., 4, 4).

    Returns:
        (..., 4, 4) ``T_a_c``.
    """
    T_a_b = _as_array(T_a_b, (4, 4), "compose: T_a_b")
    T_b_c = _as_array(T_b_c, (4, 4), "compose: T_b_c")
    return np.matmul(T_a_b, T_b_c)


def invert(T_a_b: np.ndarray) -> np.ndarray:
    """``T_b_a`` from ``T_a_b`` using ``R^T`` and ``-R^T t`` (assumes a rigid transform).

    ``-R^T t`` is computed as ``(-R^T) @ t``, the product of the negated matrix, as written by
    hand (``-R.T @ t``): the same bits, down to the sign of a zero.

    Args:
        T_a_b: (..., 4, 4).

    Returns:
        (..., 4, 4) ``T_b_a`` with bottom row exactly [0, 0, 0, 1].
    """
    T_a_b = _as_array(T_a_b, (4, 4), "invert: T_a_b")
    R_b_a = np.swapaxes(T_a_b[..., :3, :3], -1, -2)
    t_b_a = _mv(-R_b_a, T_a_b[..., :3, 3])
    return make_transform(R_b_a, t_b_a)


def transform_points(T_a_b: np.ndarray, pts_b: np.ndarray) -> np.ndarray:
    """Map points from frame b into frame a: ``pts_a = R_a_b pts_b + t_a_b``.

    ``pts_b`` is a single point (3,) or a point set (..., N, 3) whose batch dimensions ``...``
    broadcast with those of ``T_a_b``: (4,4) with (N,3) -> (N,3); (B,4,4) with (B,N,3) ->
    (B,N,3); (B,4,4) with (N,3) -> (B,N,3). For one point per transform pass
    ``pts_b[..., None, :]``, shape (B,1,3).

    Args:
        T_a_b: (..., 4, 4).
        pts_b: (3,) or (..., N, 3), metres.

    Returns:
        (3,) for a single point with a single transform, otherwise (..., N, 3); ``pts_a``.
    """
    T_a_b = _as_array(T_a_b, (4, 4), "transform_points: T_a_b")
    pts_b = _as_array(pts_b, (3,), "transform_points: pts_b")
    if pts_b.ndim == 1:
        out = transform_points(T_a_b, pts_b[None, :])
        return out[..., 0, :]
    R = T_a_b[..., :3, :3]
    t = T_a_b[..., None, :3, 3]
    return np.matmul(pts_b, np.swapaxes(R, -1, -2)) + t


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Exponential of se(3): ``T = [[exp(phi), V rho], [0, 1]]`` with ``V = J_l(phi)``.

    Args:
        xi: (..., 6) tangent vector ``[rho, phi]``: translation part (3) first, rotation part
            (3) second, matching the covariance order x, y, z, rot_x, rot_y, rot_z.

    Returns:
        (..., 4, 4) rigid transform.
    """
    xi = _as_array(xi, (6,), "se3_exp: xi")
    rho, phi = xi[..., :3], xi[..., 3:]
    return make_transform(so3_exp(phi), _mv(so3_left_jacobian(phi), rho))


def se3_log(T: np.ndarray) -> np.ndarray:
    """Logarithm of SE(3), the inverse of :func:`se3_exp`: ``phi = so3_log(R)``,
    ``rho = J_l(phi)^-1 t``.

    Args:
        T: (..., 4, 4) rigid transform.

    Returns:
        (..., 6) ``[rho, phi]``, rotation angle ``|phi|`` in [0, pi].
    """
    T = _as_array(T, (4, 4), "se3_log: T")
    phi = so3_log(T[..., :3, :3])
    rho = _mv(so3_left_jacobian_inv(phi), T[..., :3, 3])
    return np.concatenate([rho, phi], axis=-1)


# --------------------------------------------------------------------------- utilities
def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Rotation angle of ``R`` in [0, pi], as ``atan2(|vee(R - R^T)|/2, (tr R - 1)/2)``.

    Accurate near 0 and near pi, unlike ``arccos`` of the trace alone.

    Args:
        R: (..., 3, 3) rotation matrix.

    Returns:
        (...) angle, radians.
    """
    R = _as_array(R, (3, 3), "rotation_angle: R")
    sin_t = np.linalg.norm(vee(R), axis=-1)
    cos_t = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.arctan2(sin_t, cos_t)


def is_rotation(R: np.ndarray, atol: float = 1e-6) -> np.ndarray:
    """Whether ``R`` is a rotation: finite, ``|R^T R - I| <= atol`` elementwise, ``|det R - 1|
    <= atol``.

    Args:
        R: (..., 3, 3).
        atol: absolute tolerance.

    Returns:
        (...) bool.
    """
    R = _as_array(R, (3, 3), "is_rotation: R")
    finite = np.all(np.isfinite(R), axis=(-2, -1))
    Rf = np.where(finite[..., None, None], R, 0.0)
    ortho_err = np.abs(np.swapaxes(Rf, -1, -2) @ Rf - np.eye(3)).max(axis=(-2, -1))
    det_err = np.abs(np.linalg.det(Rf) - 1.0)
    return finite & (ortho_err <= atol) & (det_err <= atol)


def random_rotations(n: int, seed: int | np.random.Generator) -> np.ndarray:
    """``n`` rotations drawn uniformly (Haar measure) on SO(3).

    Args:
        n: number of rotations, >= 0.
        seed: int seed or ``numpy.random.Generator``; required (no global random state).

    Returns:
        (n, 3, 3) rotation matrices.
    """
    if seed is None:
        raise ValueError("random_rotations: an explicit seed is required")
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 0:
        raise ValueError(f"random_rotations: n must be a non-negative int, got {n!r}")
    if n == 0:
        return np.zeros((0, 3, 3))
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    return Rotation.random(int(n), rng=rng).as_matrix().reshape(int(n), 3, 3)
