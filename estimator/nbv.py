"""Next-best-view: which of a set of camera poses would teach the estimator the most.

Every track (and every held detection, a part seen in one view only) is summarised as an
:class:`NbvTrack`: its translation Gaussian N(t, P) and its rotation mixture's leading
components. A candidate view ``c`` scores

    S(c) = sum_o v_o(c) * (g_t,o(c) + rotation_weight * g_r,o(c))        [nats]

- **translation** ``g_t``: one more center measurement from ``c`` with covariance
  ``sigma^2 I`` (px^2), linearised at the track's mean with the Jacobian of the translation step
  (:func:`estimator.translation.gaussian.predict`), gives ``P' = (P^-1 + J^T J / sigma^2)^-1``;
  ``g_t = 1/2 log(det(P + e^2 I) / det(P' + e^2 I))`` with ``e = precision_rel * diameter``: the
  information about the position beyond the precision a pose needs. A view along a one-view
  track's ray gains almost nothing, one across it a lot; a part known to a millimetre gains
  nothing more.
- **rotation** ``g_r``: the mixture's leading components (at most ``max_components`` of weight
  ``>= min_weight``) are hypotheses with their renormalised weights ``w``. From ``c`` each would
  look like its nearest LINE-2D template (off-axis parts corrected by the ray's rotation as in
  :mod:`estimator.rotation.matching`); every symmetric equivalent of every template is in the index,
  so a symmetric equivalent is the same template and never a difference. ``s_ij`` is the similarity
  of two templates' gradient features (:class:`AppearanceIndex`). The view is a noisy channel that
  reports hypothesis ``j`` when ``i`` is true with probability ``s_ij^gamma / sum_k s_ik^gamma``;
  ``g_r`` is its mutual information: 0 when the hypotheses all look alike from ``c``, up to the
  entropy of ``w`` when ``c`` tells them apart.
- **visibility** ``v`` in [0, 1]: 0 when the center projects behind the camera or outside the
  image (less the part's projected radius); else the share of the part's disk in the image not
  covered by the disks of tracks closer to the camera, and 0 when the line of sight to the
  part's center passes through a wall of the bin (below its rim). Candidates where ``v`` is
  below ``min_visibility`` gain nothing from that part.

Everything is batched over candidates and tracks; 100 candidates x 30 tracks take a few tens
of ms (``python -m posefuse.bench.active --speed``).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from posefuse.estimator.core.bin_region import BinRegion
from posefuse.estimator.core.camera import Camera
from posefuse.estimator.core.geometry import invert, so3_exp
from posefuse.estimator.core.objects import ObjectModel
from posefuse.estimator.rotation.templates import TemplateBank
from posefuse.estimator.translation.gaussian import MIN_DEPTH, prior_from_first_view

N_ORIENTATIONS = 8
NO_ROTATION = np.zeros((0, 3, 3))


@dataclass(frozen=True)
class NbvConfig:
    center_sigma_px: float = 2.0  # expected std of one more center measurement
    # e: position finer than this x diameter is not worth a view. 0.05 rather than 0.02: on
    # the mixed bins of the tuning seed (python -m posefuse.bench.active --profiles mixed --scenes 4
    # --seeds mixed=4242), 0.02 spent the late views on triangulation and lost 6-9 points of
    # ADD-sym at 7-8 views; 0.05 did not
    precision_rel: float = 0.05
    max_components: int = 3  # leading rotation hypotheses compared
    min_weight: float = 0.05  # weaker components are left out
    similarity_power: float = 4.0  # gamma: how sharply a template similarity confuses
    rotation_weight: float = 1.0
    part_radius_rel: float = 0.35  # a part's disk (image, occlusion) has this x diameter radius
    min_visibility: float = 0.25
    # objects_needing_views: a track needs a view until its position is known to this x its
    # diameter (largest std) and its leading rotation component has this weight
    done_translation_rel: float = 0.03
    done_rotation_weight: float = 0.8

    def __post_init__(self) -> None:
        if self.center_sigma_px <= 0 or self.precision_rel <= 0 or self.max_components < 1:
            raise ValueError(f"invalid NBV config {self}")


@dataclass(frozen=True, eq=False)
class CandidateView:
    """A camera pose the robot can reach: T_world_cam (4, 4) and its intrinsics."""

    T_world_cam: np.ndarray
    camera: Camera


@dataclass(frozen=True, eq=False)
class NbvTrack:
    """What the score needs of one object: t_world_obj (3,) m, cov (3, 3) m^2, the leading
    rotation components R_world_obj (K, 3, 3) with weights (K,) (K = 0 when no rotation was
    measured yet), the part's diameter (m); ``key`` names it in the result."""

    key: str
    obj_id: int
    t_world_obj: np.ndarray
    cov: np.ndarray
    diameter: float
    R_components: np.ndarray
    weights: np.ndarray
    confirmed: bool = True


@dataclass(frozen=True, eq=False)
class NbvScores:
    """Candidates C, objects O: score (C,) nats; translation, rotation, visibility (C, O);
    order (C,) candidate indices, best first; keys (O,) the objects."""

    score: np.ndarray
    translation: np.ndarray
    rotation: np.ndarray
    visibility: np.ndarray
    order: np.ndarray
    keys: tuple[str, ...]

    @property
    def best(self) -> int:
        return int(self.order[0])


# ---------------------------------------------------------------------------- appearance


class AppearanceIndex:
    """The templates of one part, looked up by rotation modulo symmetry and compared.

    Lookup: a kd-tree on the quaternions (both signs) of every template's every symmetric
    equivalent ``R_template @ S^T``; the nearest one to ``R`` is the template whose look is
    closest to the part at ``R`` (the chordal quaternion distance is monotone in the angle).

    Comparison: each template's features as bits (orientation bin x 4-px cell of the RoI),
    and the same spread to the neighbouring cells and orientation bins (LINE-2D's tolerance);
    ``similarity(i, j)`` is the mean of the shares of i's features found in j's spread bits and
    of j's in i's: 1 for one template with itself, ~0.2 for unrelated ones.
    """

    CELL = 4

    def __init__(self, bank: TemplateBank, symmetries: np.ndarray):
        """symmetries: (S, 4, 4) or (S, 3, 3), the identity first (object frame)."""
        S = np.asarray(symmetries, dtype=np.float64)[:, :3, :3]
        R = np.einsum("nij,skj->nsik", bank.R_cam_obj, S).reshape(-1, 3, 3)  # R_b S^T
        q = Rotation.from_matrix(R).as_quat()
        self._tree = cKDTree(np.concatenate([q, -q]))
        self._template = np.tile(np.repeat(np.arange(len(bank)), len(S)), 2)
        self.bits, self.spread = _feature_bits(bank, self.CELL)
        self.counts = np.maximum(np.bitwise_count(self.bits).sum(1), 1).astype(np.float64)

    def nearest(self, R_cam_obj_axis: np.ndarray) -> np.ndarray:
        """(M,) template indices of (M, 3, 3) rotations of a part on the optical axis."""
        q = Rotation.from_matrix(R_cam_obj_axis.reshape(-1, 3, 3)).as_quat()
        _, k = self._tree.query(q)
        return self._template[k]

    def similarity(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """(P,) similarity in [0, 1] of templates i (P,) and j (P,)."""
        a = np.bitwise_count(self.bits[i] & self.spread[j]).sum(1) / self.counts[i]
        b = np.bitwise_count(self.bits[j] & self.spread[i]).sum(1) / self.counts[j]
        return 0.5 * (a + b)


def _feature_bits(bank: TemplateBank, cell: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, W) uint64 feature bits and their spread (3 x 3 cells, orientation +-1 bin)."""
    G = bank.config.roi_size // cell
    n = len(bank)
    grid = np.zeros((n, N_ORIENTATIONS, G, G), bool)
    rows, cols = np.nonzero(bank.feat_valid)
    grid[
        rows,
        bank.feat_label[rows, cols].astype(int) % N_ORIENTATIONS,
        np.clip(bank.feat_y[rows, cols] // cell, 0, G - 1),
        np.clip(bank.feat_x[rows, cols] // cell, 0, G - 1),
    ] = True
    labels = grid.copy()
    for dl in (-1, 1):  # orientation bins are cyclic (LINE-2D's 8 bins over 180 degrees)
        labels |= np.roll(grid, dl, axis=1)
    padded = np.pad(labels, ((0, 0), (0, 0), (1, 1), (1, 1)))
    spread = np.zeros_like(grid)
    for dy in range(3):
        for dx in range(3):
            spread |= padded[:, :, dy : dy + G, dx : dx + G]

    def pack(b: np.ndarray) -> np.ndarray:
        return np.packbits(b.reshape(n, -1), axis=1).view(np.uint64)

    return pack(grid), pack(spread)


_INDICES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def appearance_index(bank: TemplateBank, model: ObjectModel) -> AppearanceIndex:
    """The index of a bank (built once per bank, ~0.1-0.5 s, and kept while the bank lives)."""
    index = _INDICES.get(bank)
    if index is None:
        step = np.deg2rad(bank.config.symmetry_step_deg)
        index = AppearanceIndex(bank, model.symmetry_transforms(step))
        _INDICES[bank] = index
    return index


# ---------------------------------------------------------------------------- candidates


def look_at(eye: np.ndarray, target: np.ndarray, up_hint: np.ndarray) -> np.ndarray:
    """(4, 4) T_world_cam of an OpenCV camera at ``eye`` looking at ``target``; the image's
    up (-y) leans towards ``up_hint``."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z = z / np.linalg.norm(z)
    x = np.cross(z, up_hint)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, [1.0, 0.0, 0.0])
    x = x / np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = eye
    return T


def default_candidates(
    camera: Camera,
    bin_region: BinRegion | None = None,
    distances: tuple[float, ...] = (0.55, 0.75),
    polar_deg: tuple[float, ...] = (0.0, 15.0, 30.0, 40.0),
    n_azimuth: int = 8,
) -> list[CandidateView]:
    """A hemisphere over the bin: at each working distance from the floor's centre (2 cm up),
    the vertical view and rings at the given angles from the vertical, ``n_azimuth`` per ring,
    every camera looking at the centre with the image's up along +y of the bin."""
    region = bin_region or BinRegion()
    T = region.T_world_bin
    target = T[:3, :3] @ np.array([0.0, 0.0, 0.02]) + T[:3, 3]
    up = T[:3, :3] @ np.array([0.0, 1.0, 0.0])
    out = []
    for r in distances:
        for polar in polar_deg:
            azimuths = [0.0] if polar == 0 else np.arange(n_azimuth) * 2 * np.pi / n_azimuth
            for az in azimuths:
                p = np.deg2rad(polar)
                d_bin = np.array([np.sin(p) * np.cos(az), np.sin(p) * np.sin(az), np.cos(p)])
                eye = target + r * (T[:3, :3] @ d_bin)
                # the image's top towards the camera's side of the bin, as a robot holding
                # the camera over the bin's edge would (and as the front end was trained)
                radial = T[:3, :3] @ np.array([np.cos(az), np.sin(az), 0.0])
                out.append(CandidateView(look_at(eye, target, radial if polar else up), camera))
    return out


# ---------------------------------------------------------------------------- tracks


def tracks_for_nbv(estimator, max_components: int = 3) -> list[NbvTrack]:
    """The tracks of a :class:`~estimator.tracker.MultiViewEstimator` and its held detections
    (a part seen in one view: its ray with the box-depth prior of the translation step)."""
    from posefuse.estimator.tracker import CONFIRMED

    out = []
    for key in sorted(estimator.tracks):
        track = estimator.tracks[key]
        model = estimator.catalog[track.obj_id]
        R = np.zeros((0, 3, 3))
        w = np.zeros(0)
        if track.mixture is not None and track.mixture.components:
            weights = track.mixture.weights
            top = np.argsort(-weights, kind="stable")[:max_components]
            R = np.array([track.mixture.components[k].R_world_obj for k in top])
            w = weights[top]
        out.append(
            NbvTrack(
                key,
                track.obj_id,
                track.estimate.t_world_obj.copy(),
                track.estimate.cov.copy(),
                model.diameter,
                R,
                w,
                track.status == CONFIRMED,
            )
        )
    for h in estimator.held():
        if h.obj_id not in estimator.catalog or not np.isfinite(h.box_depth):
            continue  # "a part" not yet named (a generalist front end's) has no model
        model = estimator.catalog[h.obj_id]
        T_world_cam = invert(h.T_cam_world)
        f = 0.5 * (h.K[0, 0] + h.K[1, 1])
        bbox = f * model.diameter / h.box_depth
        t0, P0 = prior_from_first_view(T_world_cam, h.K, h.uv, bbox, model.diameter)
        # the center across the ray: the detection's covariance at the box depth
        J = _center_jacobian(T_world_cam, h.K, t0)
        cov = np.linalg.inv(np.linalg.inv(P0) + J.T @ np.linalg.inv(h.cov) @ J)
        key = f"held/{model.name}/{h.stamp_ns}/{h.index}"
        out.append(
            NbvTrack(key, h.obj_id, t0, cov, model.diameter, NO_ROTATION, np.zeros(0), False)
        )
    return out


def _center_jacobian(T_world_cam: np.ndarray, K: np.ndarray, t_world: np.ndarray) -> np.ndarray:
    """(2, 3) d uv / d t_world of a pinhole camera."""
    R_cw = T_world_cam[:3, :3].T
    p = R_cw @ (t_world - T_world_cam[:3, 3])
    x, y, z = p
    d = np.array([[1 / z, 0, -x / z**2], [0, 1 / z, -y / z**2]])
    return K[:2, :2] @ d @ R_cw


def needs_view(track: NbvTrack, config: NbvConfig | None = None) -> bool:
    """Whether a track's pose is still uncertain: tentative, its position not known to
    ``done_translation_rel`` x diameter, no rotation yet or a leading component too weak."""
    cfg = config or NbvConfig()
    if not track.confirmed or len(track.weights) == 0:
        return True
    std = np.sqrt(np.linalg.eigvalsh(track.cov).max())
    return bool(
        std > cfg.done_translation_rel * track.diameter
        or track.weights.max() < cfg.done_rotation_weight
    )


# ---------------------------------------------------------------------------- scoring


def score_candidates(
    tracks: list[NbvTrack],
    candidates: list[CandidateView],
    indices: dict[int, AppearanceIndex] | None = None,
    config: NbvConfig | None = None,
    bin_region: BinRegion | None = None,
) -> NbvScores:
    """Score every candidate for every track (see the module docstring).

    indices: the appearance index per obj_id (:func:`appearance_index`); a class without one
    gets no rotation gain.
    """
    cfg = config or NbvConfig()
    if not candidates:
        raise ValueError("next-best-view: no candidate views")
    n_cand = len(candidates)
    keys = tuple(t.key for t in tracks)
    if not tracks:
        z = np.zeros((n_cand, 0))
        return NbvScores(np.zeros(n_cand), z, z, z, np.arange(n_cand), keys)
    T_wc = np.stack([np.asarray(c.T_world_cam, np.float64) for c in candidates])  # (C, 4, 4)
    R_cw = T_wc[:, :3, :3].transpose(0, 2, 1)
    t_cw = -np.einsum("cij,cj->ci", R_cw, T_wc[:, :3, 3])
    K = np.stack([c.camera.K for c in candidates])  # (C, 3, 3)
    size = np.array([(c.camera.width, c.camera.height) for c in candidates], float)  # (C, 2)
    t = np.stack([tr.t_world_obj for tr in tracks])  # (O, 3)
    P = np.stack([tr.cov for tr in tracks])  # (O, 3, 3)
    diam = np.array([tr.diameter for tr in tracks])  # (O,)

    p = np.einsum("cij,oj->coi", R_cw, t) + t_cw[:, None]  # (C, O, 3) in each camera
    z = p[..., 2]
    front = z > MIN_DEPTH
    zs = np.where(front, z, 1.0)
    x, y = p[..., 0] / zs, p[..., 1] / zs
    f = 0.5 * (K[:, 0, 0] + K[:, 1, 1])  # (C,)
    u = K[:, None, 0, 0] * x + K[:, None, 0, 1] * y + K[:, None, 0, 2]
    v = K[:, None, 1, 1] * y + K[:, None, 1, 2]

    # translation: P' = (P^-1 + J^T J / sigma^2)^-1
    dxy = np.zeros((*z.shape, 2, 3))
    dxy[..., 0, 0] = 1 / zs
    dxy[..., 0, 2] = -x / zs
    dxy[..., 1, 1] = 1 / zs
    dxy[..., 1, 2] = -y / zs
    J = np.einsum("cab,cobd,cde->coae", K[:, :2, :2], dxy, R_cw)  # (C, O, 2, 3)
    info = np.linalg.inv(P)[None] + np.einsum("coai,coaj->coij", J, J) / cfg.center_sigma_px**2
    P_post = np.linalg.inv(info)
    floor = ((cfg.precision_rel * diam) ** 2)[:, None, None] * np.eye(3)  # (O, 3, 3)
    _, logdet_prior = np.linalg.slogdet(P + floor)
    _, logdet_post = np.linalg.slogdet(P_post + floor[None])
    g_t = np.maximum(0.5 * (logdet_prior[None] - logdet_post), 0.0)

    vis = _visibility(u, v, z, front, f, size, diam, T_wc[:, :3, 3], t, cfg, bin_region)
    g_r = _rotation_gain(tracks, R_cw, p, front & (vis >= cfg.min_visibility), indices, cfg)
    g_t = np.where(vis >= cfg.min_visibility, g_t, 0.0)
    weight = np.where(vis >= cfg.min_visibility, vis, 0.0)
    score = (weight * (g_t + cfg.rotation_weight * g_r)).sum(1)
    order = np.argsort(-score, kind="stable")
    return NbvScores(score, g_t, g_r, vis, order, keys)


def _visibility(u, v, z, front, f, size, diam, eyes, t, cfg, bin_region) -> np.ndarray:
    """(C, O) visible share of each part's disk (see the module docstring)."""
    r_px = cfg.part_radius_rel * diam[None] * f[:, None] / np.where(front, z, 1.0)  # (C, O)
    inside = (
        front
        & (u >= r_px)
        & (v >= r_px)
        & (u <= size[:, None, 0] - r_px)
        & (v <= size[:, None, 1] - r_px)
    )
    # occlusion by the disks of closer parts: the covered share of the disk's diameter on the
    # line between the centres, per occluder, multiplied
    du = u[:, :, None] - u[:, None, :]
    dv = v[:, :, None] - v[:, None, :]
    d = np.hypot(du, dv)  # (C, O, O): target o, occluder k
    closer = (z[:, None, :] < z[:, :, None]) & front[:, None, :]
    overlap = (r_px[:, :, None] + r_px[:, None, :] - d) / (2 * r_px[:, :, None])
    covered = np.where(closer, np.clip(overlap, 0.0, 1.0), 0.0)
    vis = np.prod(1.0 - covered, axis=2)
    if bin_region is not None:
        vis = vis * ~_behind_wall(eyes, t, bin_region)
    return np.where(inside, vis, 0.0)


def _behind_wall(eyes: np.ndarray, t: np.ndarray, region: BinRegion) -> np.ndarray:
    """(C, O) True when the segment from a camera (C, 3) to a part (O, 3) crosses a wall of
    the bin (x or y at the inner size, z between the floor and the rim; bin frame)."""
    T = region.T_world_bin
    R_bw, t_bw = T[:3, :3].T, -T[:3, :3].T @ T[:3, 3]
    e = eyes @ R_bw.T + t_bw  # (C, 3) in the bin frame
    q = t @ R_bw.T + t_bw  # (O, 3)
    half = np.array(region.size) / 2
    blocked = np.zeros((len(e), len(q)), bool)
    d = q[None] - e[:, None]  # (C, O, 3)
    for axis in (0, 1):
        for sign in (-1.0, 1.0):
            wall = sign * half[axis]
            with np.errstate(divide="ignore", invalid="ignore"):
                s = (wall - e[:, None, axis]) / d[..., axis]  # where the segment meets the plane
                hit = e[:, None] + s[..., None] * d
            other = 1 - axis
            with np.errstate(invalid="ignore"):
                blocked |= (
                    (s > 0)
                    & (s < 1)
                    & (np.abs(hit[..., other]) <= half[other])
                    & (hit[..., 2] < region.wall_height)
                    & (hit[..., 2] > 0)
                )
    return blocked


def _rotation_gain(tracks, R_cw, p, usable, indices, cfg) -> np.ndarray:
    """(C, O) mutual information between the hypotheses and what the view shows."""
    g = np.zeros(usable.shape)
    if not indices:
        return g
    for o, tr in enumerate(tracks):
        keep = tr.weights >= cfg.min_weight
        R_w = tr.R_components[keep][: cfg.max_components]
        w = tr.weights[keep][: cfg.max_components]
        index = indices.get(tr.obj_id)
        if len(w) < 2 or index is None or not usable[:, o].any():
            continue
        w = w / w.sum()
        cs = np.nonzero(usable[:, o])[0]
        Kc = len(w)
        R_cam = np.einsum("cij,kjl->ckil", R_cw[cs], R_w)  # (c, K, 3, 3)
        R_ray = _ray_rotations(p[cs, o])  # (c, 3, 3)
        R_axis = np.einsum("cji,ckjl->ckil", R_ray, R_cam)
        tpl = index.nearest(R_axis.reshape(-1, 3, 3)).reshape(len(cs), Kc)
        i, j = np.triu_indices(Kc, 1)
        s = np.ones((len(cs), Kc, Kc))
        sim = index.similarity(tpl[:, i].ravel(), tpl[:, j].ravel()).reshape(len(cs), -1)
        s[:, i, j] = sim
        s[:, j, i] = sim
        g[cs, o] = _channel_information(w, s**cfg.similarity_power)
    return g


def _channel_information(w: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Mutual information (nats) of hypotheses with prior w (K,) through channels (c, K, K)
    whose row i is proportional to the probabilities of reporting j when i is true."""
    p = s / s.sum(2, keepdims=True)
    p_out = np.einsum("i,cij->cj", w, p)
    h_out = -np.sum(p_out * np.log(np.maximum(p_out, 1e-300)), axis=1)
    h_cond = -np.einsum("i,cij->c", w, p * np.log(np.maximum(p, 1e-300)))
    return np.maximum(h_out - h_cond, 0.0)


def _ray_rotations(t_cam: np.ndarray) -> np.ndarray:
    """(M, 3, 3) rotations taking the optical axis onto the rays through t_cam (M, 3)
    (:func:`estimator.rotation.matching.ray_correction`, batched)."""
    d = t_cam / np.linalg.norm(t_cam, axis=1, keepdims=True)
    axis = np.cross([0.0, 0.0, 1.0], d)
    s = np.linalg.norm(axis, axis=1)
    angle = np.arctan2(s, d[:, 2])
    unit = np.where(s[:, None] > 1e-12, axis / np.maximum(s, 1e-12)[:, None], 0.0)
    return so3_exp(unit * angle[:, None])
