"""The verification's inner loops, compiled (numba): projecting a track's edge samples into its
views, reading the chamfer maps there, and summing what the scoring and the refinement need.

The numpy code these loops replace (:func:`estimator.verification.refinement._data_term` with
:func:`~estimator.verification.refinement._read`, and the chamfer part of
:func:`estimator.verification.verify.score_hypotheses`) is kept: it is the reference the tests
hold these kernels to, and ``RefineConfig.compiled`` / ``VerificationConfig.compiled`` = False
run it. Each numpy call there is cheap; a check makes thousands of them on arrays of a few
thousand samples, so their overhead and temporaries were most of its time. One pass per
(pose, view) over the samples that show does the same arithmetic without them
(``python -m posefuse.bench.profile_frame --numpy`` prints the step both ways). The sums
run in another order than numpy's pairwise ones, so results agree to rounding, not to the bit.

The kernels are compiled on first use and cached on disk beside this module (``cache=True``; or
in the user's cache folder, or nowhere where neither can be written);
:func:`compile_kernels` compiles them ahead of the first frame (``MultiViewEstimator.warm_up``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from posefuse.estimator.core.compiled import as_bool, as_f64, compiled

__all__ = ["as_bool", "as_f64", "chamfer_costs", "compile_kernels", "data_term", "facing_sets"]


_compiled = compiled  # the name this module's loops and its tests use


@njit(nogil=True, inline="always")
def _matmul3(X, Y):
    """(3, 3) X @ Y, written out (numba's ``@`` calls BLAS, slow for 3 x 3)."""
    out = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            out[i, j] = X[i, 0] * Y[0, j] + X[i, 1] * Y[1, j] + X[i, 2] * Y[2, j]
    return out


@njit(nogil=True, inline="always")
def _project(point, direction, A, b, bins):
    """A sample's pixel (u, v) and its edge's orientation bin: q = A p + b (A = K R, b = K t),
    uv = q_xy / q_z, the direction d turned to dq = A d and d(uv) ~ dq_xy - uv dq_z."""
    q0 = A[0, 0] * point[0] + A[0, 1] * point[1] + A[0, 2] * point[2] + b[0]
    q1 = A[1, 0] * point[0] + A[1, 1] * point[1] + A[1, 2] * point[2] + b[1]
    q2 = A[2, 0] * point[0] + A[2, 1] * point[1] + A[2, 2] * point[2] + b[2]
    d0 = A[0, 0] * direction[0] + A[0, 1] * direction[1] + A[0, 2] * direction[2]
    d1 = A[1, 0] * direction[0] + A[1, 1] * direction[1] + A[1, 2] * direction[2]
    d2 = A[2, 0] * direction[0] + A[2, 1] * direction[1] + A[2, 2] * direction[2]
    z = max(q2, 1e-6)
    u, v = q0 / z, q1 / z
    angle = math.atan2(d1 - v * d2, d0 - u * d2) % math.pi
    b_ = int(math.floor(angle / (math.pi / bins) + 0.5)) % bins
    return u, v, b_


@njit(nogil=True, inline="always")
def _sample(maps, channel, u, v, truncate):
    """Bilinear read of uint8 map ``channel`` at (u, v), in pixels, and its gradient
    (:func:`estimator.verification.edge_maps.sample_maps`, one sample)."""
    L_y, L_x = maps.shape[1], maps.shape[2]
    if not (u >= 0 and v >= 0 and u <= L_x - 1.001 and v <= L_y - 1.001):
        return truncate, 0.0, 0.0
    x0, y0 = int(math.floor(u)), int(math.floor(v))
    fx, fy = u - x0, v - y0
    v00 = float(maps[channel, y0, x0])
    v01 = float(maps[channel, y0, x0 + 1])
    v10 = float(maps[channel, y0 + 1, x0])
    v11 = float(maps[channel, y0 + 1, x0 + 1])
    top = v00 + fx * (v01 - v00)
    bottom = v10 + fx * (v11 - v10)
    scale = truncate / 255.0
    value = (top + fy * (bottom - top)) * scale
    du = ((1 - fy) * (v01 - v00) + fy * (v11 - v10)) * scale
    dv = (bottom - top) * scale
    return value, du, dv


@_compiled
def data_term(
    points,
    directions,
    contour,
    crease,
    R,
    t,
    R_cw,
    t_cw,
    K,
    maps,
    has_mask,
    bins,
    truncate,
    crease_weight,
    mask_weight,
    sample_stride,
    points_per_view,
    sigma_px,
    huber_px,
    want_jacobian,
):
    """The refinement's data term at the pose (R, t) (:func:`refinement._data_term`).

    Args:
        points, directions: (P, 3) float64 object frame; contour, crease: (V, P) bool, the
        samples scored as contour and as crease; R: (3, 3) R_world_obj; t: (3,) metres;
        R_cw: (V, 3, 3), t_cw: (V, 3) T_cam_world; K: (V, 3, 3) RoI intrinsics; maps:
        (V * bins + V, L, L) uint8, every view's chamfer maps then its mask-boundary map;
        has_mask: (V,) bool.
    Returns:
        cost; H: (6, 6) information; g: (6,) gradient, over (t, rotation) as in refinement.
    """
    V, P = contour.shape
    n_max = 2 * V * P
    r_view = np.empty(n_max, np.int64)
    r_term = np.empty(n_max, np.int64)
    r_sample = np.empty(n_max, np.int64)
    r_d = np.empty(n_max)
    r_du = np.empty(n_max)
    r_dv = np.empty(n_max)
    counts = np.zeros((V, 3))
    A = np.empty((V, 3, 3))
    b = np.empty((V, 3))
    t_cam = np.empty((V, 3))
    for v in range(V):
        R_cam = _matmul3(R_cw[v], R)
        for i in range(3):
            t_cam[v, i] = R_cw[v, i, 0] * t[0] + R_cw[v, i, 1] * t[1] + R_cw[v, i, 2] * t[2]
            t_cam[v, i] += t_cw[v, i]
        A[v] = _matmul3(K[v], R_cam)
        for i in range(3):
            b[v, i] = K[v, i, 0] * t_cam[v, 0] + K[v, i, 1] * t_cam[v, 1] + K[v, i, 2] * t_cam[v, 2]
    n = 0
    for v in range(V):
        masked = mask_weight > 0 and has_mask[v]
        for p in range(P):
            on_contour = contour[v, p]
            if not (on_contour or crease[v, p]):
                continue
            u, w, bin_ = _project(points[p], directions[p], A[v], b[v], bins)
            d, du, dv = _sample(maps, v * bins + bin_, u, w, truncate)
            term = 0 if on_contour else 1
            r_view[n], r_term[n], r_sample[n] = v, term, p
            r_d[n], r_du[n], r_dv[n] = d, du, dv
            counts[v, term] += 1
            n += 1
            if masked and on_contour:
                d, du, dv = _sample(maps, V * bins + v, u, w, truncate)
                r_view[n], r_term[n], r_sample[n] = v, 2, p
                r_d[n], r_du[n], r_dv[n] = d, du, dv
                counts[v, 2] += 1
                n += 1
    weights = np.array([1.0, crease_weight, mask_weight])
    cost = 0.0
    H = np.zeros((6, 6))
    g = np.zeros(6)
    J = np.empty(6)
    for i in range(n):
        v, term, d = r_view[i], r_term[i], r_d[i]
        scale = (
            weights[term]
            * min(float(sample_stride), points_per_view / counts[v, term])
            / (sigma_px * sigma_px)
        )
        dt = min(d, truncate)
        if dt <= huber_px:
            rho, w = dt * dt, 1.0
        else:
            rho, w = 2 * huber_px * dt - huber_px * huber_px, huber_px / max(dt, 1e-12)
        cost += scale * rho
        if not want_jacobian or not d < truncate * 0.999:
            continue
        p = r_sample[i]
        # the sample turned (R p), in the camera, the gradient through the intrinsics and the
        # projection, then to the world frame: [g_w, (R p) x g_w] (refinement._data_term)
        a0 = R[0, 0] * points[p, 0] + R[0, 1] * points[p, 1] + R[0, 2] * points[p, 2]
        a1 = R[1, 0] * points[p, 0] + R[1, 1] * points[p, 1] + R[1, 2] * points[p, 2]
        a2 = R[2, 0] * points[p, 0] + R[2, 1] * points[p, 1] + R[2, 2] * points[p, 2]
        Rv = R_cw[v]
        x = Rv[0, 0] * a0 + Rv[0, 1] * a1 + Rv[0, 2] * a2 + t_cam[v, 0]
        y = Rv[1, 0] * a0 + Rv[1, 1] * a1 + Rv[1, 2] * a2 + t_cam[v, 1]
        z = Rv[2, 0] * a0 + Rv[2, 1] * a1 + Rv[2, 2] * a2 + t_cam[v, 2]
        e0 = r_du[i] * K[v, 0, 0] + r_dv[i] * K[v, 1, 0]
        e1 = r_du[i] * K[v, 0, 1] + r_dv[i] * K[v, 1, 1]
        inv_z = 1.0 / z
        gp0, gp1 = e0 * inv_z, e1 * inv_z
        gp2 = -(e0 * x + e1 * y) * inv_z * inv_z
        for j in range(3):
            J[j] = gp0 * Rv[0, j] + gp1 * Rv[1, j] + gp2 * Rv[2, j]
        J[3] = a1 * J[2] - a2 * J[1]
        J[4] = a2 * J[0] - a0 * J[2]
        J[5] = a0 * J[1] - a1 * J[0]
        wl = w * scale
        for j in range(6):
            g[j] += J[j] * wl * d
            for k in range(6):
                H[j, k] += wl * J[j] * J[k]
    return cost, H, g


@_compiled
def chamfer_costs(
    points,
    directions,
    active,
    contour,
    R_cam,
    t_cam,
    K,
    view_of,
    dcdt,
    masks,
    has_mask,
    bins,
    truncate,
):
    """Per pose, the mean truncated chamfer of its contour and of its creases, and the mean
    distance of its contour to the mask's boundary (the sums of
    :func:`estimator.verification.verify.score_hypotheses`).

    Args:
        points, directions: (P, 3) object frame; active, contour: (N, P) bool of each pose
        (:func:`model_edges.pose_edges`); R_cam: (N, 3, 3); t_cam: (N, 3); K: (N, 3, 3);
        view_of: (N,) the view of each pose; dcdt: (V * bins, L, L) uint8; masks: (V, L, L)
        uint8 (any map where a view has none); has_mask: (V,) bool.
    Returns:
        sums: (N, 3) of the contour's, the creases' and the contour's mask distances, pixels;
        counts: (N, 2) contour and crease samples.
    """
    N, P = active.shape
    sums = np.zeros((N, 3))
    counts = np.zeros((N, 2))
    b = np.empty(3)
    for n in range(N):
        A = _matmul3(K[n], R_cam[n])
        for i in range(3):
            b[i] = K[n, i, 0] * t_cam[n, 0] + K[n, i, 1] * t_cam[n, 1] + K[n, i, 2] * t_cam[n, 2]
        v = view_of[n]
        for p in range(P):
            if not active[n, p]:
                continue
            u, w, bin_ = _project(points[p], directions[p], A, b, bins)
            d, _, _ = _sample(dcdt, v * bins + bin_, u, w, truncate)
            if contour[n, p]:
                sums[n, 0] += d
                counts[n, 0] += 1
                if has_mask[v]:
                    dm, _, _ = _sample(masks, v, u, w, truncate)
                    sums[n, 2] += dm
            else:
                sums[n, 1] += d
                counts[n, 1] += 1
    return sums, counts


@_compiled
def facing_sets(normals_t, offsets, crease, c_obj, centres):
    """Which samples show at N camera centres (:func:`model_edges.pose_edges` before the
    occlusion test; :func:`model_edges._facing` for each face): a face turns towards a centre
    c when c . n > p . n, away when c . n < p . n.

    Args:
        normals_t: (3, 2P) the samples' two face normals; offsets: (P, 2) p . n of each;
        crease: (P,) bool; c_obj: (N, 3) camera centres, object frame; centres: (N, 3) the
        viewpoints' own centres (OcclusionTable.viewpoints), or (0, 3) for none.
    Returns:
        contour: (N, P) on the occluding contour; active: (N, P) on it or on a crease with a
        face towards the camera; shared: (N, P) active with a face towards the viewpoint too
        (all False without viewpoints).
    """
    N, P = c_obj.shape[0], offsets.shape[0]
    with_viewpoints = centres.shape[0] == N
    contour = np.zeros((N, P), np.bool_)
    active = np.zeros((N, P), np.bool_)
    shared = np.zeros((N, P), np.bool_)
    for n in range(N):
        c0, c1, c2 = c_obj[n, 0], c_obj[n, 1], c_obj[n, 2]
        for p in range(P):
            k0, k1 = 2 * p, 2 * p + 1
            t0 = c0 * normals_t[0, k0] + c1 * normals_t[1, k0] + c2 * normals_t[2, k0]
            t1 = c0 * normals_t[0, k1] + c1 * normals_t[1, k1] + c2 * normals_t[2, k1]
            f0, a0 = t0 > offsets[p, 0], t0 < offsets[p, 0]
            f1, a1 = t1 > offsets[p, 1], t1 < offsets[p, 1]
            on_contour = (f0 and a1) or (a0 and f1)
            shows = on_contour or (crease[p] and (f0 or f1))
            contour[n, p], active[n, p] = on_contour, shows
            if shows and with_viewpoints:
                s0 = (
                    centres[n, 0] * normals_t[0, k0]
                    + centres[n, 1] * normals_t[1, k0]
                    + centres[n, 2] * normals_t[2, k0]
                )
                s1 = (
                    centres[n, 0] * normals_t[0, k1]
                    + centres[n, 1] * normals_t[1, k1]
                    + centres[n, 2] * normals_t[2, k1]
                )
                shared[n, p] = s0 > offsets[p, 0] or s1 > offsets[p, 1]
    return contour, active, shared


def compile_kernels() -> None:
    """Compile (or load from the disk cache) every kernel on a small input, so that the first
    frame does not wait for it."""
    P, V, bins, L = 4, 1, 8, 8
    points = np.zeros((P, 3))
    points[:, 2] = np.linspace(-0.01, 0.01, P)
    directions = np.tile(np.array([1.0, 0.0, 0.0]), (P, 1))
    shown = np.ones((V, P), bool)
    R = np.eye(3)
    t = np.array([0.0, 0.0, 0.5])
    K = np.array([[[100.0, 0.0, 4.0], [0.0, 100.0, 4.0], [0.0, 0.0, 1.0]]])
    maps = np.zeros((V * bins + V, L, L), np.uint8)
    args = (points, directions, shown, ~shown, R, t, R[None], np.zeros((V, 3)), K, maps)
    data_term(*args, np.ones(V, bool), bins, 4.0, 0.5, 1.5, 1, 40.0, 1.5, 2.0, True)
    chamfer_costs(
        points,
        directions,
        shown,
        shown,
        R[None],
        t[None],
        K,
        np.zeros(V, np.int64),
        maps[: V * bins],
        maps[:V],
        np.ones(V, bool),
        bins,
        4.0,
    )
    normals_t = np.zeros((3, 2 * P))
    normals_t[2] = 1.0
    offsets, crease = np.zeros((P, 2)), np.ones(P, bool)
    facing_sets(normals_t, offsets, crease, t[None], t[None])
    facing_sets(normals_t, offsets, crease, t[None], np.zeros((0, 3)))
