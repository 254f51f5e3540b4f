"""Bin-picking scenes like ROBI's: parts piled in a bin, seen from several cameras above it.

World frame: z up, the bin floor's top surface at z = 0, the bin centred on the origin. Parts
are dropped one after another: each takes one of its stable resting poses (with a small random
tilt and a random yaw), and is lowered straight down until it touches the bin floor or a part
already placed. The touching distance is found by casting rays down from the new part's surface
and up from the pile's surface, so parts rest on each other without interpenetrating (up to
the sampling of the surfaces, ~1 mm).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation
from trimesh.ray.ray_pyembree import RayMeshIntersector

from posefuse.estimator.core.camera import Camera
from posefuse.estimator.core.objects import Catalog, ObjectModel
from posefuse.estimator.rotation.render import MATTE, Lighting, Material, random_lighting

REALSENSE_1280x720 = Camera(np.array([[924.0, 0, 644.0], [0, 924.0, 361.0], [0, 0, 1]]), 1280, 720)


def camera_of_size(width: int, height: int) -> Camera:
    """A sensor of ``width`` x ``height`` pixels with the 1280x720 RealSense's horizontal field
    of view (focal length scaled by the width), square pixels, principal point at the image
    center: another resolution or aspect of the same kind of camera."""
    if not (16 <= width <= 8192 and 16 <= height <= 8192):
        raise ValueError(f"camera size {width}x{height}: each side must be in [16, 8192]")
    f = REALSENSE_1280x720.K[0, 0] * width / REALSENSE_1280x720.width
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]])
    return Camera(K, width, height)


INTRINSICS = {
    "realsense": REALSENSE_1280x720,
    "realsense-640": REALSENSE_1280x720.scaled(0.5),
    "ensenso": Camera(np.array([[1145.0, 0, 640.0], [0, 1145.0, 512.0], [0, 0, 1]]), 1280, 1024),
}


@dataclass(frozen=True)
class BinSpec:
    """Inner floor size (x, y), wall height and thickness, metres."""

    size: tuple[float, float] = (0.42, 0.32)
    wall_height: float = 0.08
    wall_thickness: float = 0.008


@dataclass(frozen=True)
class SceneSpec:
    n_instances: tuple[int, int] = (5, 15)  # inclusive range
    n_views: int = 8
    distance: tuple[float, float] = (0.5, 0.9)  # camera to look-at point, metres
    max_polar_deg: float = 35.0  # camera's angle from the vertical
    parts_per_scene: tuple[int, int] = (1, 3)  # how many different parts share a bin
    tilt_deg: float = 12.0  # random tilt added to a stable pose
    drop_candidates: int = 6  # placements tried per part; the lowest resting one is kept
    bin: BinSpec = field(default_factory=BinSpec)
    view_pattern: str = "around"  # "around" the bin, or an eye-in-hand "sweep" over it
    drop_region: float = 1.0  # parts are dropped over this fraction of the floor's sides

    def __post_init__(self):
        if self.view_pattern not in VIEW_PATTERNS:
            raise ValueError(
                f"view_pattern must be one of {', '.join(VIEW_PATTERNS)}, got {self.view_pattern!r}"
            )


VIEW_PATTERNS = ("around", "sweep")

# Scene profiles of `posefuse synth --profile`:
# - mixed: 5-15 parts of 1-3 types, cameras spread around the bin (our bins until now);
# - robi: one part type per bin, 20-40 of them tumbled and dropped over the middle of the bin so
#   that they pile up and hide each other as in ROBI, 8 views of an eye-in-hand sweep across the
#   bin at the same distances.
PROFILES = {
    "mixed": SceneSpec(),
    "robi": SceneSpec(
        n_instances=(20, 40),
        parts_per_scene=(1, 1),
        view_pattern="sweep",
        tilt_deg=70.0,  # tumbled, not resting flat
        drop_candidates=1,  # each part lands where it falls, on the pile
        drop_region=0.7,  # over the middle of the bin, so the parts pile up
    ),
}


@dataclass(frozen=True, eq=False)
class Instance:
    obj_id: int
    T_world_obj: np.ndarray  # (4, 4)


@dataclass(frozen=True, eq=False)
class Scene:
    """A bin with posed parts, its lighting and its camera views."""

    instances: tuple[Instance, ...]
    bin_mesh: trimesh.Trimesh
    bin_material: Material
    lighting: Lighting
    camera: Camera
    T_world_cams: np.ndarray  # (V, 4, 4)


def bin_mesh(spec: BinSpec) -> trimesh.Trimesh:
    """An open box: floor top at z = 0, inner size ``spec.size``."""
    sx, sy = spec.size
    t, h = spec.wall_thickness, spec.wall_height
    boxes = [trimesh.creation.box([sx + 2 * t, sy + 2 * t, t], _translation(0, 0, -t / 2))]
    for sign in (-1, 1):
        boxes.append(
            trimesh.creation.box([t, sy + 2 * t, h], _translation(sign * (sx + t) / 2, 0, h / 2))
        )
        boxes.append(trimesh.creation.box([sx, t, h], _translation(0, sign * (sy + t) / 2, h / 2)))
    return trimesh.util.concatenate(boxes)


def bin_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """A plastic-like albedo: a random base colour with blotches and scratches. (size, size, 3)."""
    base = rng.uniform(0.08, 0.35, size=3)
    noise = np.zeros((size, size))
    for octave in (4, 16, 64):
        coarse = rng.normal(size=(octave, octave))
        noise += (
            trimesh.util.np.kron(coarse, np.ones((size // octave, size // octave))) / octave**0.5
        )
    tex = base[None, None, :] * (1 + 0.25 * noise[..., None] / np.abs(noise).max())
    for _ in range(40):  # thin bright scratches
        r0, c0 = rng.integers(0, size, 2)
        length = int(rng.integers(10, 60))
        ang = rng.uniform(0, np.pi)
        rr = np.clip((r0 + np.arange(length) * np.sin(ang)).astype(int), 0, size - 1)
        cc = np.clip((c0 + np.arange(length) * np.cos(ang)).astype(int), 0, size - 1)
        tex[rr, cc] *= 1.6
    return np.clip(tex, 0, 1).astype(np.float32)


def _translation(x: float, y: float, z: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


class _StablePoses:
    """Stable resting orientations of each model (cached), from trimesh's convex-hull analysis."""

    def __init__(self):
        self._cache: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, model: ObjectModel) -> tuple[np.ndarray, np.ndarray]:
        key = model.mesh.identifier_hash  # the shape, not the obj_id: catalogs differ
        if key not in self._cache:
            hull = model.mesh.convex_hull
            with np.errstate(divide="ignore", invalid="ignore"):  # degenerate hull faces
                transforms, probs = trimesh.poses.compute_stable_poses(
                    model.mesh, center_mass=hull.center_mass, n_samples=1
                )
            keep = probs > 0.02
            transforms, probs = transforms[keep], probs[keep]
            self._cache[key] = (transforms, probs / probs.sum())
        return self._cache[key]


_STABLE = _StablePoses()


class _PilePieces:
    """The bin and the parts placed in it, each with its own ray intersector, built once.

    Rebuilding one intersector over the whole pile after every part grew as the square of the
    parts (placing a pile of 36 eye bolts of 41k faces took 18.7 s, 11.8 s this way); a ray
    cast straight down from inside a part's footprint can only meet a piece whose footprint
    overlaps it, so only those are asked, and the nearest of their hits is the pile's. The
    same distance as the whole pile's to float precision, not to the bit: the intersector
    works in float32 on each mesh scaled to its own box, so where two pieces are hit within
    float32 of each other the nearer may differ (one part's pose by under 1 nm in one of 4 scenes
    compared; their images equal)."""

    def __init__(self, bin_mesh: trimesh.Trimesh):
        self.pieces: list[tuple[_Caster, np.ndarray]] = []
        self.add(bin_mesh)

    def add(self, mesh: trimesh.Trimesh) -> None:
        self.pieces.append((_Caster(mesh), mesh.bounds[:, :2].copy()))

    def distance_down(self, origins: np.ndarray) -> float:
        """Smallest distance straight down (-z) from any of ``origins`` (n, 3) to the pile."""
        down = np.array([0.0, 0.0, -1.0])
        lo, hi = origins[:, :2].min(0), origins[:, :2].max(0)  # the rays' footprint
        dist = np.inf
        for caster, (piece_lo, piece_hi) in self.pieces:
            if np.all(piece_lo <= hi) and np.all(lo <= piece_hi):
                dist = min(dist, caster.distance(origins, down))
        return dist


def _drop_distance(
    part: trimesh.Trimesh,
    pile: trimesh.Trimesh,
    pieces: _PilePieces,
    rng: np.random.Generator,
) -> float:
    """How far ``part`` can move straight down (-z) before touching ``pile`` (the bin and the
    parts placed, as one mesh and as ``pieces``)."""
    down = np.array([0.0, 0.0, -1.0])
    samples, _ = trimesh.sample.sample_surface(part, 3000, seed=int(rng.integers(2**31)))
    part_pts = np.vstack([part.vertices, samples])
    dist = pieces.distance_down(part_pts)
    lo, hi = part.bounds[:, :2]
    pile_pts = np.vstack([pile.vertices, _pile_samples(pile)])
    inside = np.all((pile_pts[:, :2] >= lo) & (pile_pts[:, :2] <= hi), axis=1)
    if inside.any():
        up = _Caster(part).distance(pile_pts[inside], -down)
        dist = min(dist, up)
    return dist


def _pile_samples(pile: trimesh.Trimesh) -> np.ndarray:
    """Dense surface samples of the pile (seeded by its size, so reproducible), cached."""
    key = (len(pile.faces), round(float(pile.area), 12))
    if _PILE_CACHE.get("key") != key:
        pts, _ = trimesh.sample.sample_surface(pile, 20000, seed=len(pile.faces))
        _PILE_CACHE.update(key=key, pts=np.asarray(pts))
    return _PILE_CACHE["pts"]


_PILE_CACHE: dict = {}


class _Caster:
    """A mesh's ray intersector with its triangles and face normals read once (trimesh checks
    its cache by hashing the mesh's arrays at every read)."""

    def __init__(self, mesh: trimesh.Trimesh):
        self.intersector = RayMeshIntersector(mesh)
        self.triangles = np.asarray(mesh.triangles)  # (F, 3, 3)
        self.face_normals = np.asarray(mesh.face_normals)  # (F, 3)

    def distance(self, origins: np.ndarray, direction: np.ndarray) -> float:
        """Smallest distance along ``direction`` (3,) from any of ``origins`` (n, 3) to the
        mesh (inf when no ray meets it)."""
        dirs = np.broadcast_to(direction, origins.shape).copy()
        tri = self.intersector.intersects_first(origins, dirs)
        hit = tri >= 0
        if not hit.any():
            return np.inf
        fn = self.face_normals[tri[hit]]
        p0 = self.triangles[tri[hit], 0]
        t = np.einsum("ij,ij->i", p0 - origins[hit], fn) / np.einsum("ij,ij->i", dirs[hit], fn)
        return float(np.min(t))


def place_instances(
    models: list[ObjectModel], n: int, spec: SceneSpec, rng: np.random.Generator
) -> list[Instance]:
    """Drop ``n`` parts drawn from ``models`` into the bin, one after another.

    Each part tries ``spec.drop_candidates`` random positions and orientations and keeps the one
    that comes to rest lowest, as a part tipped into a bin slides into the gaps of the pile
    rather than balancing on top of it.
    """
    pile = bin_mesh(spec.bin)
    pieces = _PilePieces(pile)
    sx, sy = spec.bin.size
    instances: list[Instance] = []
    for _ in range(n):
        model = models[int(rng.integers(len(models)))]
        transforms, probs = _STABLE(model)
        best = None
        for _ in range(spec.drop_candidates):
            T = transforms[rng.choice(len(transforms), p=probs)]
            tilt_axis = np.array([*rng.normal(size=2), 0.0])
            tilt = Rotation.from_rotvec(
                tilt_axis / np.linalg.norm(tilt_axis) * np.deg2rad(rng.uniform(0, spec.tilt_deg))
            )
            yaw = Rotation.from_euler("z", rng.uniform(0, 2 * np.pi))
            R = (yaw * tilt).as_matrix() @ T[:3, :3]
            posed = model.mesh.copy()
            posed.apply_transform(_pose(R, np.zeros(3)))
            lo, hi = posed.bounds
            half = np.array([sx, sy]) / 2 * spec.drop_region
            room = np.maximum(half - (hi - lo)[:2] / 2 - 0.003, 0.0)
            centre_xy = rng.uniform(-room, room)
            start_z = pile.bounds[1, 2] + 0.02 - lo[2]
            shift = np.array([*(centre_xy - (lo[:2] + hi[:2]) / 2), start_z])
            posed.apply_translation(shift)
            drop = _drop_distance(posed, pile, pieces, rng)
            if not np.isfinite(drop):
                continue
            drop = max(drop - 2e-4, 0.0)  # leave a 0.2 mm gap: touching, never intersecting
            rest_z = posed.bounds[0, 2] - drop
            if best is None or rest_z < best[0]:
                best = (rest_z, R, shift - [0, 0, drop], posed, drop)
        if best is None:
            continue
        _, R, t, posed, drop = best
        posed.apply_translation([0, 0, -drop])
        instances.append(Instance(model.obj_id, _pose(R, t)))
        pile = trimesh.util.concatenate([pile, posed])
        pieces.add(posed)
    return instances


def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def look_at(eye: np.ndarray, target: np.ndarray, up_hint: np.ndarray) -> np.ndarray:
    """T_world_cam of an OpenCV camera at ``eye`` whose optical axis (+z) points at ``target``;
    image up (-y) leans towards ``up_hint``."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, up_hint)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return _pose(np.stack([x, y, z], axis=1), eye)


def sample_views(spec: SceneSpec, rng: np.random.Generator) -> np.ndarray:
    """(V, 4, 4) T_world_cam on a hemisphere above the bin, looking into it: spread around it,
    or (``spec.view_pattern == "sweep"``) along one pass of a hand-held camera across it."""
    if spec.view_pattern == "sweep":
        return _sweep_views(spec, rng)
    views = []
    base_az = rng.uniform(0, 2 * np.pi)
    for k in range(spec.n_views):
        # Azimuths spread around the bin (as a robot moving around it would), polar angles random.
        az = base_az + 2 * np.pi * k / spec.n_views + rng.uniform(-0.3, 0.3)
        polar = np.deg2rad(rng.uniform(5.0, spec.max_polar_deg))
        r = rng.uniform(*spec.distance)
        target = np.array([*rng.uniform(-0.03, 0.03, 2), 0.02])
        eye = target + r * np.array(
            [np.sin(polar) * np.cos(az), np.sin(polar) * np.sin(az), np.cos(polar)]
        )
        roll_hint = np.array(
            [np.cos(az + np.pi + rng.normal(0, 0.3)), np.sin(az + np.pi + rng.normal(0, 0.3)), 0.0]
        )
        views.append(look_at(eye, target, -roll_hint))
    return np.stack(views)


def _sweep_views(spec: SceneSpec, rng: np.random.Generator) -> np.ndarray:
    """An eye-in-hand sweep: the camera passes over the bin along one direction, from one side's
    largest polar angle through the vertical to the other's, at a distance that drifts a little,
    always looking at the middle of the bin."""
    views = []
    direction = rng.uniform(0, 2 * np.pi)
    radius = rng.uniform(*spec.distance)
    lo, hi = spec.distance
    for k in range(spec.n_views):
        s = -1.0 + 2.0 * k / max(spec.n_views - 1, 1)
        polar = np.deg2rad(s * spec.max_polar_deg + rng.normal(0, 2.0))
        az = direction + rng.normal(0, 0.15)
        r = float(np.clip(radius + rng.normal(0, 0.02), lo, hi))
        target = np.array([*rng.uniform(-0.02, 0.02, 2), 0.02])
        eye = target + r * np.array(
            [np.sin(polar) * np.cos(az), np.sin(polar) * np.sin(az), np.cos(polar)]
        )
        # the image's up stays along the sweep, as a wrist camera keeps its orientation
        up = np.array([np.cos(direction + np.pi / 2), np.sin(direction + np.pi / 2), 0.0])
        views.append(look_at(eye, target, up))
    return np.stack(views)


def make_scene(
    catalog: Catalog,
    spec: SceneSpec,
    seed: int,
    camera: Camera = REALSENSE_1280x720,
    obj_ids: list[int] | None = None,
) -> Scene:
    """A random bin scene: parts, lighting, bin appearance and camera views, all from ``seed``."""
    rng = np.random.default_rng(seed)
    ids = sorted(catalog) if obj_ids is None else list(obj_ids)
    k = int(rng.integers(spec.parts_per_scene[0], min(spec.parts_per_scene[1], len(ids)) + 1))
    chosen = sorted(rng.choice(ids, size=k, replace=False).tolist())
    n = int(rng.integers(spec.n_instances[0], spec.n_instances[1] + 1))
    instances = place_instances([catalog[i] for i in chosen], n, spec, rng)
    texture = bin_texture(rng)
    bin_material = Material(
        color=(1.0, 1.0, 1.0),
        diffuse=MATTE.diffuse,
        specular=0.15,
        shininess=20.0,
        reflect=0.03,
        fresnel0=0.04,
        texture=texture,
        texture_size=float(rng.uniform(0.15, 0.4)),
    )
    lighting = random_lighting(int(rng.integers(2**31)))
    views = sample_views(spec, rng)
    return Scene(tuple(instances), bin_mesh(spec.bin), bin_material, lighting, camera, views)
