"""Ray-cast renderer on trimesh + embree: instance ids, depth, normals and a shaded image.

One :class:`Renderer` holds a static set of posed meshes (a bin scene, or one object for
templates) and renders it from any camera pose. The material model is meant for machined metal:
a weak diffuse term, strong Blinn-Phong highlights from directional lights, and a Fresnel-weighted
mirror reflection of a procedural environment (bright ceiling panels over a dim room), so parts
show the specular highlights and reflections that make them hard.

Images are RGB uint8 (convert to BGR before ``cv2.imwrite``); depth is the z of the hit point in
the camera frame in metres, 0 where no surface was hit; normals are unit vectors in the camera
frame; instance ids are the ids given per mesh, -1 for background.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np
import trimesh
from trimesh.ray.ray_pyembree import RayMeshIntersector

from posefuse.estimator.core.camera import Camera
from posefuse.estimator.core.geometry import invert

BACKGROUND = -1


@dataclass(frozen=True)
class Material:
    """Surface appearance. Colours are linear RGB in [0, 1].

    Attributes:
        color: (3,) albedo; for metals it also tints reflections.
        diffuse: Lambertian weight.
        specular: Blinn-Phong highlight weight; shininess its exponent.
        reflect: weight of the mirror reflection of the environment.
        fresnel0: reflectance at normal incidence (Schlick); metals ~0.5-0.9.
        texture: optional (H, W, 3) float albedo texture in [0, 1], mapped triplanarly in the
            world frame with ``texture_size`` metres per repeat (used for the bin).
    """

    color: tuple[float, float, float] = (0.7, 0.7, 0.72)
    diffuse: float = 0.25
    specular: float = 0.9
    shininess: float = 60.0
    reflect: float = 0.6
    fresnel0: float = 0.55
    texture: np.ndarray | None = field(default=None, compare=False, repr=False)
    texture_size: float = 0.2


METAL = Material()
CHROME = Material(
    color=(0.8, 0.8, 0.82), diffuse=0.08, specular=1.2, shininess=120.0, reflect=0.85, fresnel0=0.7
)
MATTE = Material(
    color=(0.5, 0.5, 0.5), diffuse=0.9, specular=0.05, shininess=8.0, reflect=0.0, fresnel0=0.04
)


@dataclass(frozen=True)
class DirectionalLight:
    """A light at infinity. direction: (3,) unit vector from the scene towards the light, in the
    world frame; color: (3,) linear radiance."""

    direction: tuple[float, float, float]
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)


@dataclass(frozen=True, eq=False)
class Lighting:
    """Lights, ambient term and an equirectangular environment map (world frame, z up)."""

    lights: tuple[DirectionalLight, ...]
    ambient: tuple[float, float, float] = (0.08, 0.08, 0.08)
    environment: np.ndarray | None = None  # (He, We, 3) float linear radiance
    background: tuple[float, float, float] = (0.05, 0.05, 0.05)


def make_environment(
    seed: int, width: int = 256, height: int = 128, n_panels: int = 4
) -> np.ndarray:
    """A procedural room: dim walls, a brighter ceiling and bright rectangular light panels.

    Returns (height, width, 3) float32 linear radiance, equirectangular: column = azimuth
    (0..2pi), row = polar angle from +z (0..pi).
    """
    rng = np.random.default_rng(seed)
    polar = (np.arange(height) + 0.5) / height * np.pi
    up = np.cos(polar)[:, None, None]  # 1 at zenith, -1 at nadir
    env = np.empty((height, width, 3), np.float32)
    env[:] = 0.15 + 0.25 * np.clip(up, 0, 1)
    tint = rng.uniform(0.9, 1.1, size=3).astype(np.float32)
    env *= tint
    for _ in range(n_panels):
        row = int(rng.uniform(0.05, 0.4) * height)
        col = int(rng.uniform(0, 1) * width)
        h = max(2, int(rng.uniform(0.04, 0.1) * height))
        w = max(3, int(rng.uniform(0.05, 0.15) * width))
        cols = np.arange(col, col + w) % width
        env[row : row + h, cols] = rng.uniform(3.0, 6.0)
    return cv2.GaussianBlur(env, (0, 0), 1.0)


def random_lighting(seed: int) -> Lighting:
    """Lighting from above with random directions and strengths, and a random environment."""
    rng = np.random.default_rng(seed)
    lights = []
    for i in range(int(rng.integers(1, 3))):
        az = rng.uniform(0, 2 * np.pi)
        el = rng.uniform(np.deg2rad(50), np.deg2rad(88))
        direction = (np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el))
        strength = rng.uniform(0.7, 1.1) * (1.0 if i == 0 else 0.5)
        color = strength * rng.uniform(0.92, 1.0, size=3)
        lights.append(DirectionalLight(tuple(direction), tuple(color)))
    return Lighting(
        lights=tuple(lights),
        ambient=tuple(np.full(3, rng.uniform(0.05, 0.12))),
        environment=make_environment(int(rng.integers(2**31))),
    )


DEFAULT_LIGHTING = Lighting(
    lights=(
        DirectionalLight((0.3, -0.2, 0.93)),
        DirectionalLight((-0.5, 0.4, 0.77), (0.4, 0.4, 0.4)),
    ),
    environment=make_environment(0),
)


@dataclass(frozen=True, eq=False)
class RenderResult:
    """instance: (H, W) int32 ids, -1 background; depth: (H, W) float32 metres, 0 = no hit;
    normals: (H, W, 3) float32 unit normals in the camera frame; image: (H, W, 3) uint8 RGB."""

    instance: np.ndarray
    depth: np.ndarray
    normals: np.ndarray
    image: np.ndarray


@lru_cache(maxsize=16)
def _pixel_rays(K_bytes: bytes, dist_bytes: bytes, width: int, height: int) -> np.ndarray:
    camera = Camera(np.frombuffer(K_bytes).reshape(3, 3), width, height, np.frombuffer(dist_bytes))
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    rays = camera.back_project(np.stack([u, v], axis=-1).reshape(-1, 2), 1.0)
    rays.setflags(write=False)
    return rays  # (H*W, 3) with z = 1


def pixel_rays(camera: Camera) -> np.ndarray:
    """(H*W, 3) camera-frame rays through every pixel centre, scaled to z = 1, row-major."""
    return _pixel_rays(camera.K.tobytes(), camera.dist.tobytes(), camera.width, camera.height)


class Renderer:
    """A static scene of posed meshes, rendered by casting one ray per pixel.

    Args:
        meshes: object meshes in their own frames, metres.
        poses: (4, 4) T_world_obj per mesh (identity if None).
        ids: instance id per mesh (default 0, 1, ...); must be >= 0.
        materials: per mesh (default METAL).
        smooth_angle_deg: normals are interpolated across edges flatter than this angle.
    """

    def __init__(
        self,
        meshes: Sequence[trimesh.Trimesh],
        poses: Sequence[np.ndarray] | None = None,
        ids: Sequence[int] | None = None,
        materials: Sequence[Material] | None = None,
        smooth_angle_deg: float = 35.0,
    ):
        if len(meshes) == 0:
            raise ValueError("Renderer needs at least one mesh")
        poses = [np.eye(4)] * len(meshes) if poses is None else list(poses)
        ids = list(range(len(meshes))) if ids is None else [int(i) for i in ids]
        materials = [METAL] * len(meshes) if materials is None else list(materials)
        if not (len(poses) == len(ids) == len(materials) == len(meshes)):
            raise ValueError("Renderer: meshes, poses, ids and materials must have equal lengths")
        if min(ids) < 0:
            raise ValueError("Renderer: instance ids must be >= 0 (-1 means background)")
        tris, corner_normals, face_mesh = [], [], []
        self._posed: list[trimesh.Trimesh] = []
        for k, (mesh, T) in enumerate(zip(meshes, poses, strict=True)):
            T = np.asarray(T, dtype=np.float64)
            smooth = trimesh.graph.smooth_shade(mesh, angle=np.deg2rad(smooth_angle_deg))
            verts = smooth.vertices @ T[:3, :3].T + T[:3, 3]
            normals = np.asarray(smooth.vertex_normals) @ T[:3, :3].T
            tris.append(verts[smooth.faces])
            corner_normals.append(normals[smooth.faces])
            face_mesh.append(np.full(len(smooth.faces), k, np.int32))
            self._posed.append(trimesh.Trimesh(verts, smooth.faces, process=False))
        self.triangles = np.concatenate(tris)  # (F, 3, 3)
        self.corner_normals = np.concatenate(corner_normals)  # (F, 3, 3)
        self.face_mesh = np.concatenate(face_mesh)  # (F,)
        scene = trimesh.Trimesh(
            self.triangles.reshape(-1, 3),
            np.arange(len(self.triangles) * 3).reshape(-1, 3),
            process=False,
        )
        self.face_normals = np.asarray(scene.face_normals)
        self._intersector = RayMeshIntersector(scene)
        self._single: dict[int, RayMeshIntersector] = {}
        self.ids = np.asarray(ids, np.int32)
        self.materials = materials

    # ------------------------------------------------------------------ casting
    def _cast(
        self,
        origin: np.ndarray,
        dirs: np.ndarray,
        intersector=None,
        triangles=None,
        face_normals=None,
    ):
        intersector = intersector or self._intersector
        triangles = self.triangles if triangles is None else triangles
        face_normals = self.face_normals if face_normals is None else face_normals
        origins = np.broadcast_to(origin, dirs.shape)
        tri = intersector.intersects_first(np.ascontiguousarray(origins), dirs)
        hit = np.flatnonzero(tri >= 0)
        tri = tri[hit]
        fn = face_normals[tri]
        d = dirs[hit]
        t = np.einsum("ij,ij->i", triangles[tri, 0] - origins[hit], fn) / np.einsum(
            "ij,ij->i", d, fn
        )
        return hit, tri, t

    def render(
        self,
        camera: Camera,
        T_world_cam: np.ndarray,
        lighting: Lighting = DEFAULT_LIGHTING,
        shadows: bool = True,
    ) -> RenderResult:
        """Render the scene seen by ``camera`` at pose ``T_world_cam`` (4, 4)."""
        T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
        R, origin = T_world_cam[:3, :3], T_world_cam[:3, 3]
        rays_cam = pixel_rays(camera)
        norm = np.linalg.norm(rays_cam, axis=1, keepdims=True)
        dirs = (rays_cam / norm) @ R.T
        hit, tri, t = self._cast(origin, dirs)
        H, W = camera.height, camera.width
        instance = np.full(H * W, BACKGROUND, np.int32)
        depth = np.zeros(H * W, np.float32)
        normals_cam = np.zeros((H * W, 3), np.float32)
        color = np.tile(np.asarray(lighting.background, np.float32), (H * W, 1))
        if len(hit):
            mesh_idx = self.face_mesh[tri]
            instance[hit] = self.ids[mesh_idx]
            depth[hit] = t / norm[hit, 0]  # z of the hit in the camera frame
            points = origin + dirs[hit] * t[:, None]
            geo = self.face_normals[tri]
            with np.errstate(divide="ignore", invalid="ignore"):
                bary = trimesh.triangles.points_to_barycentric(self.triangles[tri], points)
                n = np.einsum("ij,ijk->ik", bary, self.corner_normals[tri])
                n /= np.linalg.norm(n, axis=1, keepdims=True)
            bad = ~np.all(np.isfinite(n), axis=1)  # degenerate (zero-area) triangles
            n[bad] = geo[bad]
            view = -dirs[hit]
            flip = np.einsum("ij,ij->i", geo, view) < 0
            n[flip] *= -1
            geo[flip] *= -1
            normals_cam[hit] = n @ R
            color[hit] = self._shade(points, n, geo, view, mesh_idx, lighting, shadows)
        image = _to_srgb8(color).reshape(H, W, 3)
        return RenderResult(
            instance=instance.reshape(H, W),
            depth=depth.reshape(H, W),
            normals=normals_cam.reshape(H, W, 3),
            image=image,
        )

    def _shade(self, points, n, geo, view, mesh_idx, lighting: Lighting, shadows: bool):
        out = np.zeros((len(points), 3), np.float32)
        n_dot_v = np.clip(np.einsum("ij,ij->i", n, view), 0.0, 1.0)
        reflected = 2 * n_dot_v[:, None] * n - view
        env = (
            _sample_environment(lighting.environment, reflected)
            if lighting.environment is not None
            else None
        )
        visibility = []
        for light in lighting.lights:
            ldir = np.asarray(light.direction, np.float64)
            ldir = ldir / np.linalg.norm(ldir)
            if shadows:
                start = points + geo * 1e-4
                blocked = self._intersector.intersects_any(
                    start, np.broadcast_to(ldir, start.shape).copy()
                )
                visibility.append(~blocked)
            else:
                visibility.append(np.ones(len(points), bool))
        for m in np.unique(mesh_idx):
            sel = mesh_idx == m
            mat = self.materials[m]
            albedo = np.broadcast_to(np.asarray(mat.color, np.float32), (int(sel.sum()), 3))
            if mat.texture is not None:
                albedo = _triplanar(mat.texture, points[sel], n[sel], mat.texture_size)
            ns, vs = n[sel], view[sel]
            acc = albedo * np.asarray(lighting.ambient, np.float32)
            for light, vis in zip(lighting.lights, visibility, strict=True):
                ldir = np.asarray(light.direction, np.float64)
                ldir = ldir / np.linalg.norm(ldir)
                lc = np.asarray(light.color, np.float32)
                n_dot_l = np.clip(ns @ ldir, 0.0, 1.0) * vis[sel]
                half = vs + ldir
                half /= np.maximum(np.linalg.norm(half, axis=1, keepdims=True), 1e-12)
                spec = np.clip(np.einsum("ij,ij->i", ns, half), 0.0, 1.0) ** mat.shininess
                acc = acc + mat.diffuse * albedo * (n_dot_l[:, None] * lc)
                acc = acc + mat.specular * ((spec * (n_dot_l > 0) * vis[sel])[:, None] * lc)
            if env is not None and mat.reflect > 0:
                fresnel = mat.fresnel0 + (1 - mat.fresnel0) * (1 - n_dot_v[sel]) ** 5
                acc = acc + mat.reflect * fresnel[:, None] * env[sel] * albedo
            out[sel] = acc
        return out

    # ------------------------------------------------------------------ full masks
    def render_mask(self, camera: Camera, T_world_cam: np.ndarray, mesh_index: int) -> np.ndarray:
        """(H, W) bool silhouette of one mesh alone, as if nothing occluded it.

        Casts rays only inside the box its vertices project to, against that mesh alone.
        """
        T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
        posed = self._posed[mesh_index]
        T_cam_world = invert(T_world_cam)
        pts_cam = posed.vertices @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
        mask = np.zeros((camera.height, camera.width), bool)
        front = pts_cam[:, 2] > 1e-6
        if not front.any():
            return mask
        uv = camera.project(pts_cam[front])
        margin = 2
        u0 = int(max(0, np.floor(uv[:, 0].min()) - margin))
        v0 = int(max(0, np.floor(uv[:, 1].min()) - margin))
        u1 = int(min(camera.width, np.ceil(uv[:, 0].max()) + margin + 1))
        v1 = int(min(camera.height, np.ceil(uv[:, 1].max()) + margin + 1))
        if u0 >= u1 or v0 >= v1:
            return mask
        if mesh_index not in self._single:
            self._single[mesh_index] = RayMeshIntersector(posed)
        rays = (
            pixel_rays(camera).reshape(camera.height, camera.width, 3)[v0:v1, u0:u1].reshape(-1, 3)
        )
        dirs = rays @ T_world_cam[:3, :3].T
        hit = self._single[mesh_index].intersects_any(
            np.ascontiguousarray(np.broadcast_to(T_world_cam[:3, 3], dirs.shape)), dirs
        )
        mask[v0:v1, u0:u1] = hit.reshape(v1 - v0, u1 - u0)
        return mask


def _sample_environment(env: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Nearest-texel lookup of world directions (N, 3) in an equirectangular map."""
    h, w = env.shape[:2]
    d = dirs / np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-12)
    polar = np.arccos(np.clip(d[:, 2], -1, 1))
    azimuth = np.mod(np.arctan2(d[:, 1], d[:, 0]), 2 * np.pi)
    rows = np.clip((polar / np.pi * h).astype(int), 0, h - 1)
    cols = np.clip((azimuth / (2 * np.pi) * w).astype(int), 0, w - 1)
    return env[rows, cols]


def _triplanar(texture: np.ndarray, points: np.ndarray, n: np.ndarray, size: float) -> np.ndarray:
    """Albedo from a texture projected along the world axis closest to each normal."""
    h, w = texture.shape[:2]
    major = np.argmax(np.abs(n), axis=1)
    a = np.where(major == 0, points[:, 1], points[:, 0])
    b = np.where(major == 2, points[:, 1], points[:, 2])
    cols = (np.mod(a / size, 1.0) * w).astype(int) % w
    rows = (np.mod(b / size, 1.0) * h).astype(int) % h
    return texture[rows, cols].astype(np.float32)


def _to_srgb8(linear: np.ndarray) -> np.ndarray:
    """Clamp linear radiance to [0, 1] with a soft shoulder and apply the sRGB curve."""
    x = np.clip(linear, 0.0, None)
    x = x / (1.0 + 0.15 * x)  # gentle highlight roll-off instead of hard clipping
    x = np.clip(x / (1.0 / 1.15), 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.clip(srgb * 255.0 + 0.5, 0, 255).astype(np.uint8)
