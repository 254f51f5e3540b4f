"""The baselines of the paper's Tables I and II, on the same detections and LINE-2D features.

- **Simultaneous ablation** (Table II): our translation step, but each view's rotation from
  templates at 9 distances scored on a RoI cut at the image's own scale around the projected
  center, without the scale-aware re-crop (:class:`MultiScaleMatcher`).
- **CosyPose-style RGB** (Table I): per view, LINE-2D with templates at 9 distances gives a full
  6D pose per detection: the rotation of the best template, the depth of its distance, the
  position from the detection's center. Then the multi-view fusion CosyPose does when the
  cameras are known (:func:`fuse_candidates`): candidates of one class in different views are
  matched by their symmetry-aware pose distance, each object keeps the consensus of one
  candidate per view, and its pose is refined by minimising the symmetric reprojection error
  over its views.
- **CosyPose-style RGBD**: the same, with each view's scale taken from the depth image: the
  median depth in the mask places the part, the two-step matcher measures the rotation at that
  scale, and the rendered depth of the matched pose is aligned with the measured one.

The 9 distances are made from the canonical bank by scaling its feature positions about the
center, which is what rendering at another distance gives under weak perspective; so every
method scores the same features, and only the use of the scale differs.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares
from trimesh.ray.ray_pyembree import RayMeshIntersector

from posefuse.estimator.core.geometry import so3_exp
from posefuse.estimator.rotation.matching import (
    RotationMatcher,
    RotationMeasurement,
    ray_correction,
    select_hypotheses,
)

# candidate matching thresholds, x diameter: the best of 0.1-2.4 for each baseline on the
# full benchmark's data (RGB candidates are off in depth by up to the template spacing, so they
# only fuse with a loose gate; with depth, a tight gate keeps instances apart)
MATCH_THRESHOLD_RGB = 1.2
MATCH_THRESHOLD_RGBD = 0.2
N_DISTANCES = 9
DISTANCES = np.geomspace(0.45, 0.95, N_DISTANCES)  # metres: the bin cell's working range


class MultiScaleMatcher:
    """A bank scored at 9 distances at a known image position, without re-cropping.

    ``measure`` has the interface of :class:`RotationMatcher` (the simultaneous ablation uses
    only the position of ``t_cam_obj``, never its depth); ``best`` gives the full 6D answer of
    one detection for the CosyPose-style baseline.
    """

    def __init__(self, matcher: RotationMatcher, distances: np.ndarray = DISTANCES):
        self.matcher = matcher
        self.bank = matcher.bank
        self.config = matcher.config
        self.distances = np.asarray(distances, float)
        self._layouts: dict[float, tuple[int, np.ndarray, np.ndarray]] = {}

    def _layout(self, focal: float) -> tuple[int, np.ndarray, np.ndarray]:
        """(RoI side, (D*N, F) gather index, (D*N, F) weights) for a camera's focal length."""
        key = round(float(focal), 3)
        if key not in self._layouts:
            bank = self.bank
            cfg = bank.config
            scales = bank.z_r / self.distances * (focal / cfg.focal)  # apparent size ratio
            T = max(cfg.pyramid_T)
            size = int(np.ceil(cfg.roi_size * scales.max() / T) * T)
            c, C = (cfg.roi_size - 1) / 2.0, (size - 1) / 2.0
            index = []
            for s in scales:
                x = np.clip(np.round((bank.feat_x - c) * s + C), 0, size - 1).astype(np.int64)
                y = np.clip(np.round((bank.feat_y - c) * s + C), 0, size - 1).astype(np.int64)
                index.append(bank.feat_label.astype(np.int64) * size * size + y * size + x)
            weight = np.tile(self.matcher._weight, (len(scales), 1))
            self._layouts[key] = (size, np.concatenate(index), weight)
        return self._layouts[key]

    def scores(self, image, K, uv, mask=None) -> np.ndarray:
        """(D, N) similarity of every template at every distance, centred on uv (2,)."""
        size, index, weight = self._layout(0.5 * (K[0, 0] + K[1, 1]))
        C = (size - 1) / 2.0
        A = np.array([[1.0, 0.0, C - uv[0]], [0.0, 1.0, C - uv[1]]])
        roi = cv2.warpAffine(
            cv2.cvtColor(image, cv2.COLOR_RGB2BGR),
            A,
            (size, size),
            borderMode=cv2.BORDER_REPLICATE,
        )
        roi_mask = None
        if mask is not None:
            roi_mask = cv2.warpAffine(
                mask.astype(np.uint8) * 255, A, (size, size), flags=cv2.INTER_NEAREST
            )
            k = 2 * self.config.mask_dilation_px + 1
            roi_mask = cv2.dilate(roi_mask, np.ones((k, k), np.uint8))
        response = self.matcher.response_maps(roi, roi_mask).reshape(-1)
        return (response[index] * weight).sum(1).reshape(len(self.distances), len(self.bank))

    def best(self, image, K, uv, mask=None) -> tuple[float, int, float]:
        """(distance in metres, template index, similarity) of the best match at uv."""
        s = self.scores(image, K, uv, mask)
        d, k = np.unravel_index(int(np.argmax(s)), s.shape)
        return float(self.distances[d]), int(k), float(s[d, k])

    def measure(self, image, K, t_cam_obj, mask=None) -> list[RotationMeasurement]:
        if t_cam_obj[2] <= 0:
            return []
        uv = K[:2, :2] @ (t_cam_obj[:2] / t_cam_obj[2]) + K[:2, 2]
        best_distance = self.scores(image, K, uv, mask).max(0)  # (N,) the best of 9 distances
        R_ray = ray_correction(t_cam_obj)
        return select_hypotheses(best_distance, self.bank.R_cam_obj, R_ray, self.config)


class TimedMatcher:
    """Wraps a matcher and records the seconds of each ``measure`` call in ``times``."""

    def __init__(self, inner, times: list[float]):
        self.inner = inner
        self.bank = inner.bank
        self.times = times

    def measure(self, *args, **kwargs):
        start = time.perf_counter()
        out = self.inner.measure(*args, **kwargs)
        self.times.append(time.perf_counter() - start)
        return out


# ---------------------------------------------------------------------------- per-view 6D


@dataclass(frozen=True, eq=False)
class Candidate:
    """One per-view 6D pose of a detection. T_*: (4, 4); K: (3, 3)."""

    view: int  # index of the view in the scene's sequence
    obj_id: int
    score: float
    T_cam_obj: np.ndarray
    T_world_cam: np.ndarray
    K: np.ndarray

    @property
    def T_world_obj(self) -> np.ndarray:
        return self.T_world_cam @ self.T_cam_obj


def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def rgb_candidate(multi: MultiScaleMatcher, image, camera, det) -> tuple[np.ndarray, float]:
    """(T_cam_obj (4, 4), score) from the 9-distance templates at the detection's center."""
    z, k, score = multi.best(image, camera.K, det.center_uv, det.mask)
    t = camera.back_project(det.center_uv, z)
    return _pose(ray_correction(t) @ multi.bank.R_cam_obj[k], t), score


class DepthAligner:
    """The depth of a part's center from a depth image, given its mask and a rotation guess.

    Casts rays through (up to ``n_rays``) masked pixels with a depth at the model posed at the
    guess, and moves the part along its center's ray by the median difference between measured
    and modelled depth (the visible surface lies in front of the center by an amount that
    depends on the rotation).
    """

    def __init__(self, model, n_rays: int = 300):
        self.model = model
        self.intersector = RayMeshIntersector(model.mesh)
        self.n_rays = n_rays

    def surface_depth(self, depth: np.ndarray, mask: np.ndarray) -> float | None:
        z = depth[mask & (depth > 0)]
        return float(np.median(z)) if len(z) >= 10 else None

    def align(self, T_cam_obj, depth, mask, camera) -> np.ndarray:
        """T_cam_obj moved along its center's ray to fit the measured depth."""
        v, u = np.nonzero(mask & (depth > 0))
        if len(u) < 10:
            return T_cam_obj
        pick = np.linspace(0, len(u) - 1, min(self.n_rays, len(u))).astype(int)
        uv = np.stack([u[pick], v[pick]], 1).astype(float)
        rays = camera.back_project(uv, 1.0)  # (n, 3) with z = 1
        R, t = T_cam_obj[:3, :3], T_cam_obj[:3, 3]
        origins = np.tile(-R.T @ t, (len(rays), 1))
        dirs = rays @ R  # R^T applied to each ray
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        locations, index, _ = self.intersector.intersects_location(
            origins, dirs, multiple_hits=False
        )
        if len(index) < 10:
            return T_cam_obj
        z_model = (locations @ R.T + t)[:, 2]
        dz = float(np.median(depth[v[pick][index], u[pick][index]] - z_model))
        out = T_cam_obj.copy()
        out[:3, 3] = t * (t[2] + dz) / t[2]
        return out


def rgbd_candidate(
    matcher: RotationMatcher, aligner: DepthAligner, image, depth, camera, det, multi
) -> tuple[np.ndarray, float]:
    """(T_cam_obj, score) with the scale from the depth image (RGB only when it has none)."""
    z_surface = aligner.surface_depth(depth, det.mask) if det.mask is not None else None
    if z_surface is None:
        return rgb_candidate(multi, image, camera, det)
    t = camera.back_project(det.center_uv, z_surface + 0.25 * aligner.model.diameter)
    T, score = np.eye(4), 0.0
    for _ in range(2):  # rotation at this scale, then the depth that fits it, twice
        found = matcher.measure(image, camera.K, t, det.mask)
        if not found:
            return _pose(np.eye(3), t), 0.0
        T = aligner.align(_pose(found[0].R_cam_obj, t), depth, det.mask, camera)
        t, score = T[:3, 3], found[0].confidence
    return T, score


# ---------------------------------------------------------------------------- fusion


@dataclass(frozen=True, eq=False)
class FusedObject:
    obj_id: int
    T_world_obj: np.ndarray  # (4, 4)
    score: float
    n_views: int


class ClassGeometry:
    """Points and symmetries of one class for pose distances and reprojection."""

    def __init__(self, model, n_points: int = 50, symmetry_step_deg: float = 5.0, seed: int = 0):
        rng = np.random.default_rng(seed)
        pts = np.asarray(model.points, float)
        self.points = pts[rng.choice(len(pts), min(n_points, len(pts)), replace=False)]
        self.symmetries = model.symmetry_transforms(np.deg2rad(symmetry_step_deg))  # (S, 4, 4)
        self.diameter = float(model.diameter)

    def distances(self, Ta: np.ndarray, Tb: np.ndarray) -> np.ndarray:
        """(A, B) symmetric pose distance: min over symmetries of the mean point distance."""
        p = self.points
        Pa = Ta[:, None, :3, :3] @ p.T + Ta[:, None, :3, 3:]  # (A, 1, 3, P)
        TbS = Tb[:, None] @ self.symmetries[None]  # (B, S, 4, 4)
        Pb = TbS[..., :3, :3] @ p.T + TbS[..., :3, 3:]  # (B, S, 3, P)
        d = np.linalg.norm(Pa[:, None] - Pb[None], axis=3).mean(-1)  # (A, B, S)
        return d.min(-1)


def _project(K, T_cam_obj, pts):
    p = pts @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    z = np.maximum(p[:, 2:], 1e-6)
    return (p[:, :2] / z) @ K[:2, :2].T + K[:2, 2]


def refine(geometry: ClassGeometry, members: list[Candidate], T0: np.ndarray) -> np.ndarray:
    """T_world_obj minimising the symmetric reprojection error over the members' views:
    each view's model points projected with the object pose against the same points
    projected with that view's own candidate, under the symmetry that fits best."""
    p = geometry.points
    targets = [_project(c.K, c.T_cam_obj, p) for c in members]
    T_cam_world = [np.linalg.inv(c.T_world_cam) for c in members]
    T = T0
    for _ in range(2):  # choose each view's symmetry, solve, and again
        syms = []
        for c, Tcw, uv in zip(members, T_cam_world, targets, strict=True):
            err = [
                np.linalg.norm(_project(c.K, Tcw @ T @ S, p) - uv, axis=1).mean()
                for S in geometry.symmetries
            ]
            syms.append(geometry.symmetries[int(np.argmin(err))])

        def residuals(x, T=T, syms=syms):
            Tx = _pose(so3_exp(x[:3]) @ T[:3, :3], T[:3, 3] + x[3:])
            out = [
                _project(c.K, Tcw @ Tx @ S, p) - uv
                for c, Tcw, S, uv in zip(members, T_cam_world, syms, targets, strict=True)
            ]
            return np.concatenate(out).ravel()

        sol = least_squares(residuals, np.zeros(6), loss="soft_l1", f_scale=2.0, max_nfev=50)
        T = _pose(so3_exp(sol.x[:3]) @ T[:3, :3], T[:3, 3] + sol.x[3:])
    return T


def fuse_candidates(
    candidates: list[Candidate], geometries: dict[int, ClassGeometry], threshold: float = 0.2
) -> list[FusedObject]:
    """Object-level consensus of per-view candidates with known cameras.

    Per class, in order of score, each candidate not yet used seeds an object that takes, from
    every other view, the unused candidate nearest to it in symmetric pose distance if that is
    below ``threshold`` x diameter; objects seen in two views or more are refined by
    :func:`refine`. The score of an object is the sum of its members' scores.
    """
    out: list[FusedObject] = []
    for obj_id in sorted({c.obj_id for c in candidates}):
        cands = sorted(
            (c for c in candidates if c.obj_id == obj_id), key=lambda c: (-c.score, c.view)
        )
        geometry = geometries[obj_id]
        T = np.stack([c.T_world_obj for c in cands])
        D = geometry.distances(T, T)
        views = np.array([c.view for c in cands])
        used = np.zeros(len(cands), bool)
        limit = threshold * geometry.diameter
        for i in range(len(cands)):
            if used[i]:
                continue
            members = [i]
            used[i] = True
            for v in sorted(set(views) - {views[i]}):
                pool = np.flatnonzero((views == v) & ~used & (D[i] < limit))
                if len(pool):
                    j = int(pool[np.argmin(D[i, pool])])
                    members.append(j)
                    used[j] = True
            chosen = [cands[j] for j in members]
            T_obj = cands[i].T_world_obj
            if len(chosen) >= 2:
                T_obj = refine(geometry, chosen, T_obj)
            out.append(FusedObject(obj_id, T_obj, float(sum(c.score for c in chosen)), len(chosen)))
    return out
