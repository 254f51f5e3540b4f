"""Edges of a model, for verifying and refining a pose across views (D2CO): the model side.

Model side (:func:`model_edges`): points sampled along the edges of the mesh (decimated to a
few thousand faces), each with its edge's 3D direction and the normals of the two faces that
meet there. At a pose, a point lies on the *occluding contour* when one of its faces turns
towards the camera and the other away; it lies on a *visible crease* when its faces meet at a
sharp angle and one of them faces the camera (:func:`pose_edges`). A sample the part hides
from itself is left out: the ray from the camera meets the mesh first. The answer depends only
on where the camera stands around the part, so it is looked up by viewpoint
(:class:`OcclusionTable`), cast once per viewpoint and sample. The samples that show are
projected into a view (:func:`project_edges`, :func:`project_shown`) to read the image side's
maps (:mod:`estimator.verification.edge_maps`).

The front end's mask also gives points inside it, which a pose's silhouette should cover
(:func:`silhouette_misses`): where the part shows, its silhouette must be.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from posefuse.estimator.verification import kernels
from posefuse.estimator.verification.edge_maps import EdgeConfig

__all__ = [
    "ModelEdges",
    "OcclusionTable",
    "model_edges",
    "pose_edges",
    "project_edges",
    "project_shown",
    "silhouette_misses",
]


def fibonacci_sphere(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere: the Fibonacci lattice, n >= 1."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = i * np.pi * (3.0 - np.sqrt(5.0))  # the golden angle
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


@dataclass(eq=False)
class OcclusionTable:
    """Which edge samples the part hides from itself, by viewpoint, remembered as poses ask.

    Whether a sample is hidden depends only on where the camera stands in the object frame.
    That place is snapped to a *viewpoint*: its direction from the object's origin to the
    nearest of ``directions``, its distance to the nearest radius ``diameter * ratio**k``. A
    viewpoint's answer for a sample is the ray cast from the viewpoint's own camera centre to
    the sample, made the first time a pose from that viewpoint asks, and kept (:func:`pose_edges`
    asks only for samples that show from the viewpoint as from the camera). The answer thus
    depends on the viewpoint alone, never on which poses asked before: any order of the same
    poses gives the same answers. At most ``max_rows`` viewpoints are kept, one byte per sample
    each (``max_rows * P`` bytes at most, taken as rows fill); when full, the table starts
    again (the answers stay the same, only their cost changes).

    points: (P, 3) the samples, object frame, metres; directions: (D, 3) unit; mesh: the mesh
    the rays meet; diameter: metres; ratio: of consecutive radii, in (1, 4].
    """

    points: np.ndarray
    mesh: trimesh.Trimesh
    diameter: float
    directions: np.ndarray
    ratio: float
    max_rows: int = 4096
    _tree: cKDTree = field(init=False, repr=False)
    _row_of: dict = field(init=False, repr=False, default_factory=dict)
    # (max_rows, P) uint8 per viewpoint and sample: 0 not asked yet, 1 shows, 2 hidden
    _answer: np.ndarray = field(init=False, repr=False)
    rays_cast: int = field(init=False, default=0)  # rays cast so far, for profiling

    def __post_init__(self) -> None:
        if not 1.0 < self.ratio <= 4.0 or self.max_rows < 1:
            raise ValueError(f"OcclusionTable: ratio in (1, 4] and max_rows >= 1, got {self}")
        self._tree = cKDTree(self.directions)
        self._answer = np.zeros((self.max_rows, len(self.points)), np.uint8)  # pages as filled

    def viewpoints(self, c_obj: np.ndarray) -> tuple[list[tuple[int, int]], np.ndarray]:
        """The viewpoints of N camera centres c_obj (N, 3), object frame: their keys (shell,
        direction) and their own camera centres (N, 3). A centre at the origin, or not finite,
        gets the viewpoint of a camera one diameter away along +z."""
        c = np.asarray(c_obj, float).reshape(-1, 3)
        r = np.linalg.norm(c, axis=1)
        usable = np.isfinite(r) & (r > 0)
        unit = np.where(usable[:, None], c / np.where(usable, r, 1.0)[:, None], [0.0, 0.0, 1.0])
        _, direction = self._tree.query(unit)
        # the radius bounded (1e-3 to 1e6 diameters), not the shell's index, so any ratio snaps
        # a camera to a radius within the ratio of its own
        scaled = np.clip(np.where(usable, r, self.diameter) / self.diameter, 1e-3, 1e6)
        shell = np.round(np.log(scaled) / np.log(self.ratio)).astype(int)
        centres = self.directions[direction] * (self.diameter * self.ratio**shell)[:, None]
        return list(zip(shell.tolist(), direction.tolist(), strict=True)), centres

    def hidden(
        self,
        keys: list[tuple[int, int]],
        centres: np.ndarray,
        ask: np.ndarray,
        columns: np.ndarray | None = None,
    ) -> np.ndarray:
        """(N, Q) bool: of the samples ``ask`` (N, Q) bool, those the part hides from each
        viewpoint (keys and centres (N, 3) of :meth:`viewpoints`); False where not asked.
        ``columns`` (Q,) names the samples the Q columns stand for (None: all P, in order), so a
        subset of the samples shares the answers of the whole (:meth:`ModelEdges.subset`)."""
        cols = np.arange(len(self.points)) if columns is None else np.asarray(columns, np.intp)
        new = list(dict.fromkeys(k for k in keys if k not in self._row_of))
        if len(self._row_of) + len(new) > self.max_rows:
            self._row_of.clear()
            self._answer = np.zeros(self._answer.shape, np.uint8)  # fresh pages
            new = list(dict.fromkeys(keys))
        if len(new) > self.max_rows:  # more viewpoints in one call than the table holds
            out = np.zeros(ask.shape, bool)
            n_idx, q_idx = np.nonzero(ask)
            out[n_idx, q_idx] = self._cast_pairs(centres[n_idx], cols[q_idx])
            return out
        for k in new:
            self._row_of[k] = len(self._row_of)
        rows = np.array([self._row_of[k] for k in keys], np.intp)
        # (N, Q): every column of the rows when all are asked for, else the columns named
        answer = self._answer[rows] if columns is None else self._answer[np.ix_(rows, cols)]
        need = ask & (answer == 0)
        if need.any():
            n_idx, q_idx = np.nonzero(need)
            # a viewpoint asked twice in one call casts each of its samples once
            flat, first = np.unique(rows[n_idx] * len(self.points) + cols[q_idx], return_index=True)
            hits = self._cast_pairs(centres[n_idx[first]], cols[q_idx[first]])
            self._answer.reshape(-1)[flat] = np.where(hits, 2, 1)
            answer = self._answer[rows] if columns is None else self._answer[np.ix_(rows, cols)]
        return (answer == 2) & ask

    def _cast_pairs(self, centres: np.ndarray, sample: np.ndarray) -> np.ndarray:
        """(M,) bool: whether the mesh lies between each sample (M,) and its camera centre
        (M, 3)."""
        self.rays_cast += len(sample)
        return _hidden_from(self.mesh, self.points[sample], centres, self.diameter)


def _hidden_from(
    mesh: trimesh.Trimesh, points: np.ndarray, centres: np.ndarray, diameter: float
) -> np.ndarray:
    """(M,) bool: whether the mesh lies between each point (M, 3) and its camera centre (M, 3).

    The ray is cast from the point towards the camera, from 0.5% of the diameter off it: any hit
    is surface in between (nothing of the part lies behind the camera). The same test as the
    first hit from the camera, without computing where rays hit.
    """
    to_camera = centres - points
    to_camera /= np.linalg.norm(to_camera, axis=1)[:, None]
    start = points + 0.005 * diameter * to_camera
    return np.asarray(mesh.ray.intersects_any(start, to_camera), bool)


@dataclass(frozen=True, eq=False)
class ModelEdges:
    """Edge samples of one model, object frame, metres.

    points: (P, 3); directions: (P, 3) unit edge directions; normals: (P, 2, 3) unit normals of
    the two faces meeting at the point's edge; crease: (P,) bool, the faces meet at a sharp angle.
    spacing: metres of edge between consecutive samples (None: unknown, as for hand-made sets).
    """

    points: np.ndarray
    directions: np.ndarray
    normals: np.ndarray
    crease: np.ndarray
    diameter: float
    mesh: trimesh.Trimesh | None = None  # the decimated mesh, for the occlusion test
    spacing: float | None = None
    # self-occlusion by viewpoint, filled as poses ask (None: rays cast for every pose)
    occlusion: OcclusionTable | None = None
    # which of the table's samples these are (None: all of them, in order; see subset)
    occlusion_columns: np.ndarray | None = None
    _subsets: dict = field(default_factory=dict, repr=False)

    def subset(self, stride: int) -> ModelEdges:
        """Every ``stride``-th sample (stride 1: this model itself), as a model of its own whose
        spacing is ``stride`` times wider; it shares the mesh and the occlusion table, so what
        one has cast the other reads. Made once per stride and kept.

        Returns:
            ModelEdges of ceil(P / stride) samples.
        """
        if stride < 1:
            raise ValueError(f"ModelEdges.subset: stride must be >= 1, got {stride}")
        if stride == 1:
            return self
        if stride not in self._subsets:
            take = np.arange(0, len(self.points), stride)
            parent_columns = (
                take if self.occlusion_columns is None else self.occlusion_columns[take]
            )
            self._subsets[stride] = ModelEdges(
                self.points[take],
                self.directions[take],
                self.normals[take],
                self.crease[take],
                self.diameter,
                self.mesh,
                None if self.spacing is None else self.spacing * stride,
                self.occlusion,
                parent_columns,
            )
        return self._subsets[stride]

    @cached_property
    def _facing_terms(self) -> tuple[np.ndarray, np.ndarray]:
        """(3, 2P) the two face normals of every sample, contiguous for one matrix product, and
        (P, 2) each face's plane offset p . n_k."""
        P = len(self.points)
        normals_t = np.ascontiguousarray(self.normals.reshape(-1, 3).T)
        return normals_t, np.einsum("pki,pi->pk", self.normals, self.points).reshape(P, 2)

    @cached_property
    def _points_and_directions(self) -> np.ndarray:
        """(P, 2, 3) each sample's point and edge direction, read together."""
        return np.stack([self.points, self.directions], axis=1)

    def samples_for(self, count_at_finest: float) -> float:
        """How many of this model's samples cover the edge length that ``count_at_finest``
        samples cover at the finest spacing, diameter / 80 (the same for every ``max_points``);
        a model sampled at that spacing (its last sample a little nearer) needs exactly the
        count."""
        if self.spacing is None:
            return count_at_finest
        return count_at_finest * min(1.0, (self.diameter / 80.0) / self.spacing)


def surface_deviation(a: trimesh.Trimesh, b: trimesh.Trimesh, samples: int = 500) -> float:
    """How far apart two surfaces lie, metres: the larger of the 95th percentiles of the
    distance from ``samples`` seeded points of each to the other."""
    _, a_to_b, _ = trimesh.proximity.closest_point(b, a.sample(samples, seed=0))
    _, b_to_a, _ = trimesh.proximity.closest_point(a, b.sample(samples, seed=0))
    return float(max(np.percentile(a_to_b, 95), np.percentile(b_to_a, 95)))


def decimated(mesh: trimesh.Trimesh, max_faces: int, max_deviation: float) -> trimesh.Trimesh:
    """``mesh`` with at most ``max_faces`` faces, or twice as many and so on, the fewest
    whose surface lies within ``max_deviation`` metres of the mesh's
    (:func:`surface_deviation`); the mesh itself when none of fewer faces does.

    Quadric decimation to 2,000 faces keeps the procedural parts within 0.7% of their
    diameter. Real CAD meshes fare worse, with their fine detail (threads, teeth) and seams
    where faces meet without sharing an edge: ITODD's screw (10,458 faces) lies 12 mm off at
    2,000 faces on a 57 mm part and 1 mm at 4,000; the Siléane gear (14,020 faces) 9.7 mm at
    2,000 on 116 mm, 0.1 mm at 8,000.
    """
    faces = max_faces
    while faces < len(mesh.faces):
        smaller = mesh.simplify_quadric_decimation(face_count=faces)
        if surface_deviation(smaller, mesh) <= max_deviation:
            return smaller
        faces *= 2
    return mesh


def model_edges(mesh: trimesh.Trimesh, diameter: float, config: EdgeConfig) -> ModelEdges:
    """Sample the edges of ``mesh`` (object frame, metres) where two faces meet.

    Flat edges (faces at less than 1 degree) are left out: they are never a crease, and on the
    occluding contour their neighbours stand in for them. Samples are spaced evenly along all
    edges laid end to end, every ``diameter / 80`` or wider to keep at most ``max_points``.
    """
    mesh = decimated(mesh, config.max_faces, config.max_deviation_frac * diameter)
    adjacency = mesh.face_adjacency  # (E, 2) faces
    edges = mesh.face_adjacency_edges  # (E, 2) vertices
    angles = mesh.face_adjacency_angles  # (E,)
    keep = angles > np.deg2rad(1.0)
    adjacency, edges, angles = adjacency[keep], edges[keep], angles[keep]
    if not len(edges):  # no two faces meet at an angle: nothing for the edges to say
        empty = np.zeros((0, 3))
        return ModelEdges(
            empty, empty, np.zeros((0, 2, 3)), np.zeros(0, bool), float(diameter), mesh
        )
    a = mesh.vertices[edges[:, 0]]
    b = mesh.vertices[edges[:, 1]]
    length = np.linalg.norm(b - a, axis=1)
    # evenly along all edges laid end to end: spacing d / 80, or wider to keep max_points
    cum = np.cumsum(length)
    n = int(min(config.max_points, max(1, np.ceil(cum[-1] / (diameter / 80.0)))))
    pos = (np.arange(n) + 0.5) * (cum[-1] / n)
    edge = np.minimum(np.searchsorted(cum, pos), len(length) - 1)
    frac = np.clip((pos - (cum[edge] - length[edge])) / np.maximum(length[edge], 1e-12), 0, 1)
    # plain arrays, not trimesh's tracked ones: every operation on those pays for a hash check
    points = np.asarray(a[edge] + frac[:, None] * (b - a)[edge]).view(np.ndarray)
    directions = np.asarray((b - a)[edge] / np.maximum(length[edge], 1e-12)[:, None]).view(
        np.ndarray
    )
    normals = np.asarray(mesh.face_normals[adjacency[edge]]).view(np.ndarray)  # (P, 2, 3)
    crease = angles[edge] > np.deg2rad(config.crease_deg)
    occlusion = None
    if config.occlusion_directions:
        occlusion = OcclusionTable(
            points,
            mesh,
            float(diameter),
            fibonacci_sphere(config.occlusion_directions),
            config.occlusion_shell_ratio,
        )
    return ModelEdges(
        points, directions, normals, crease, float(diameter), mesh, cum[-1] / n, occlusion
    )


def _facing(edges: ModelEdges, c_obj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which of each sample's two faces turn towards, and which away from, N camera centres
    c_obj (N, 3), object frame: (N, P, 2) bool each (a face edge-on to the camera is neither).
    (p - c) . n_k < 0 faces the camera, i.e. c . n_k > p . n_k: one (N, 3) x (3, 2P) product."""
    normals_t, offsets = edges._facing_terms
    toward = (c_obj @ normals_t).reshape(len(c_obj), len(edges.points), 2)
    return toward > offsets, toward < offsets


def pose_edges(
    edges: ModelEdges, R_cam_obj: np.ndarray, t_cam_obj: np.ndarray, compiled: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The edge samples that show at each of N poses, object frame.

    A sample lies on the *occluding contour* when one of its two faces turns towards the camera
    and the other away, on a *visible crease* when its faces meet at more than ``crease_deg``
    and one of them faces the camera.

    Args:
        R_cam_obj: (N, 3, 3). t_cam_obj: (N, 3) metres. compiled: the faces by
        :func:`estimator.verification.kernels.facing_sets`, else by numpy (the reference).
    Returns:
        points: (N, P, 3); directions: (N, P, 3) unit, along the edge; active: (N, P) bool, on
        the contour or a visible crease; contour: (N, P) bool, on the occluding contour.
    """
    N, P = len(R_cam_obj), len(edges.points)
    c_obj = -np.einsum("nji,nj->ni", R_cam_obj, t_cam_obj)  # camera centre, object frame
    table = edges.occlusion if edges.mesh is not None else None
    if compiled:
        keys, centres = table.viewpoints(c_obj) if table is not None else ([], np.zeros((0, 3)))
        normals_t, offsets = edges._facing_terms
        f64 = kernels.as_f64  # one layout: one compiled signature
        contour, active, shared = kernels.facing_sets(
            f64(normals_t), f64(offsets), kernels.as_bool(edges.crease), f64(c_obj), f64(centres)
        )
    else:
        faces, turns_away = _facing(edges, c_obj)
        contour = (faces[..., 0] & turns_away[..., 1]) | (turns_away[..., 0] & faces[..., 1])
        active = contour | (edges.crease[None] & (faces[..., 0] | faces[..., 1]))
        if table is not None:
            keys, centres = table.viewpoints(c_obj)
            faces_there, _ = _facing(edges, centres)
            shared = active & (faces_there[..., 0] | faces_there[..., 1])
    if table is not None:
        # hidden by the part itself, from the table of viewpoints, where the sample turns a
        # face to the viewpoint as well; a sample that does not (a face nearly edge-on to the
        # camera, turned away from a viewpoint a degree or two off) would send the
        # viewpoint's ray into the part, and casts its own ray from the camera instead
        hidden = table.hidden(keys, centres, shared, edges.occlusion_columns)
        n_idx, p_idx = np.nonzero(active & ~shared)
        if len(n_idx):
            hidden[n_idx, p_idx] = _hidden_from(
                edges.mesh, edges.points[p_idx], c_obj[n_idx], edges.diameter
            )
        active &= ~hidden
        contour &= active
    elif edges.mesh is not None:
        # hidden by the part itself: the ray from the camera meets the surface first
        n_idx, p_idx = np.nonzero(active)
        if len(n_idx):
            hidden = _hidden_from(edges.mesh, edges.points[p_idx], c_obj[n_idx], edges.diameter)
            active[n_idx[hidden], p_idx[hidden]] = False
            contour &= active
    points = np.broadcast_to(edges.points, (N, P, 3))
    directions = np.broadcast_to(edges.directions, (N, P, 3))
    return points, directions, active, contour


def project_edges(
    points: np.ndarray,
    directions: np.ndarray,
    R_cam_obj: np.ndarray,
    t_cam_obj: np.ndarray,
    K: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Edge samples of N poses in an image.

    Args:
        points, directions: (N, P, 3) object frame (:func:`pose_edges`). R_cam_obj: (N, 3, 3).
        t_cam_obj: (N, 3). K: (3, 3) or (N, 3, 3).
    Returns:
        uv: (N, P, 2) pixels; angle: (N, P) direction of the projected edge in [0, pi);
        pts_cam: (N, P, 3) metres.
    """
    K = np.broadcast_to(K, (len(R_cam_obj), 3, 3))
    R_t = np.swapaxes(R_cam_obj, 1, 2)
    pts_cam = np.matmul(points, R_t) + t_cam_obj[:, None]
    dirs_cam = np.matmul(directions, R_t)
    z = np.maximum(pts_cam[..., 2], 1e-6)
    xy = pts_cam[..., :2] / z[..., None]
    K2_t = np.swapaxes(K[:, :2, :2], 1, 2)
    uv = np.matmul(xy, K2_t) + K[:, None, :2, 2]
    # d(uv)/d(direction): the projected direction, up to scale
    dxy = (dirs_cam[..., :2] - xy * dirs_cam[..., 2:3]) / z[..., None]
    duv = np.matmul(dxy, K2_t)
    angle = np.mod(np.arctan2(duv[..., 1], duv[..., 0]), np.pi)
    return uv, angle, pts_cam


def project_shown(
    edges: ModelEdges,
    shown: np.ndarray,
    R_cam_obj: np.ndarray,
    t_cam_obj: np.ndarray,
    K: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`project_edges` of only the samples that show, of N poses: a pose shows a third of
    its samples or fewer, and scoring reads no others.

    Args:
        shown: (N, P) bool (``active`` of :func:`pose_edges`). R_cam_obj: (N, 3, 3). t_cam_obj:
        (N, 3). K: (N, 3, 3).
    Returns:
        pose: (M,) the pose of each shown sample, ascending; sample: (M,) its index into the
        model's samples; uv: (M, 2) pixels; angle: (M,) projected edge direction in [0, pi).
    """
    pose, sample = np.nonzero(shown)
    M = len(pose)
    # per pose, K R and K t take a sample to homogeneous pixels q in one product: uv = q_xy / q_z
    # (K's last row is 0 0 1, so q_z is the depth), and the edge's direction d to dq = K R d
    A = np.asarray(K) @ R_cam_obj  # (N, 3, 3)
    b = np.einsum("nij,nj->ni", K, t_cam_obj)  # (N, 3)
    both = edges._points_and_directions
    q = np.empty((M, 2, 3))
    starts = np.searchsorted(pose, np.arange(len(R_cam_obj) + 1))
    for n in np.flatnonzero(np.diff(starts)):
        sl = slice(starts[n], starts[n + 1])
        q[sl] = (both[sample[sl]].reshape(-1, 3) @ A[n].T).reshape(-1, 2, 3)
        q[sl, 0] += b[n]
    z = np.maximum(q[:, 0, 2], 1e-6)
    uv = q[:, 0, :2] / z[:, None]
    # d(uv) along the edge, up to the positive factor 1 / z: dq_xy - uv dq_z
    duv = q[:, 1, :2] - uv * q[:, 1, 2:3]
    angle = np.mod(np.arctan2(duv[:, 1], duv[:, 0]), np.pi)
    return pose, sample, uv, angle


def silhouette_misses(
    mesh: trimesh.Trimesh,
    R_cam_obj: np.ndarray,
    t_cam_obj: np.ndarray,
    K: np.ndarray,
    points: list[np.ndarray],
) -> np.ndarray:
    """The share of each pose's image points that its silhouette leaves uncovered: the ray
    through the point misses the mesh. All poses' rays are cast in one call.

    Args:
        R_cam_obj: (N, 3, 3); t_cam_obj: (N, 3) metres; K: (N, 3, 3) intrinsics of the points'
        pixels; points: N arrays (Q_n, 2) of pixel coordinates (Q_n may be 0).
    Returns:
        (N,) in [0, 1]; 0 for a pose without points.
    """
    counts = np.array([len(p) for p in points], np.intp)
    out = np.zeros(len(points))
    if counts.sum() == 0:
        return out
    pose = np.repeat(np.arange(len(points)), counts)
    uv1 = np.concatenate([np.asarray(p, float).reshape(-1, 2) for p in points])
    uv1 = np.concatenate([uv1, np.ones((len(uv1), 1))], axis=1)
    # the ray through each pixel, camera frame, then turned into the object frame; it starts at
    # the camera centre, c = -R^T t
    rays_cam = np.einsum("nij,nj->ni", np.linalg.inv(K)[pose], uv1)
    directions = np.einsum("nji,nj->ni", R_cam_obj[pose], rays_cam)
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    origins = -np.einsum("nji,nj->ni", R_cam_obj, t_cam_obj)[pose]
    hit = np.asarray(mesh.ray.intersects_any(origins, directions), bool)
    missed = np.bincount(pose, weights=~hit, minlength=len(points))
    return np.where(counts > 0, missed / np.maximum(counts, 1), 0.0)
