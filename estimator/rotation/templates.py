"""TemplateBank: LINE-2D templates of one object at one canonical distance (paper Section V-A).

Viewpoints come from a subdivided icosahedron (the directions from the object to the camera),
each combined with in-plane rotations about the optical axis. For a symmetric object only the
fundamental region is kept: a rotation is kept when no symmetric equivalent of it is closer to
the identity, so each appearance is rendered once. Every template is rendered with the object
at the canonical translation ``[0, 0, z_r]`` into a square RoI of ``l_r`` pixels, and
``cv2.linemod`` picks its gradient features (positions and quantised orientations) from the
masked rendering.

``z_r`` is chosen per object so that its diameter spans ``fill * l_r`` pixels with focal length
``focal`` (the default focal matches the RealSense-like camera, so the template perspective is
that of a part at about 0.7 m).

Banks are cached on disk, keyed by a hash of the mesh, its symmetries and the parameters.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import trimesh
from tqdm import tqdm

from posefuse.estimator.core.camera import Camera
from posefuse.estimator.core.geometry import rotation_angle
from posefuse.estimator.core.objects import ObjectModel
from posefuse.estimator.rotation.render import DirectionalLight, Lighting, Material, Renderer

CACHE_ENV = "POSEFUSE_CACHE"
CACHE_VERSION = 5  # 3: in-plane turns as image rotations; 4, 5: where they save renders

# Templates are rendered with lights fixed to the camera (headlight and two fills; directions
# from the part towards the light, camera frame), so a template's shading depends on the view
# only.
TEMPLATE_LIGHTS_CAM = (
    ((0.0, 0.0, -1.0), (0.9, 0.9, 0.9)),
    ((-0.6, -0.7, -0.4), (0.5, 0.5, 0.5)),
    ((0.7, -0.3, -0.6), (0.35, 0.35, 0.35)),
)
TEMPLATE_MATERIAL = Material(
    color=(0.7, 0.7, 0.72), diffuse=0.6, specular=0.5, shininess=40.0, reflect=0.0
)


@dataclass(frozen=True)
class TemplateConfig:
    roi_size: int = 128  # l_r, pixels; a multiple of both pyramid T values
    fill: float = 0.8  # the diameter spans this fraction of the RoI at z_r
    focal: float = 924.0  # pixels
    subdivisions: int = 2  # icosphere: 0 -> 12, 1 -> 42, 2 -> 162, 3 -> 642 viewpoints
    inplane_step_deg: float = 10.0
    n_features: int = 63
    weak_threshold: float = 10.0
    strong_threshold: float = 55.0
    pyramid_T: tuple[int, int] = (4, 8)
    symmetry_step_deg: float = 5.0  # discretisation of continuous symmetries for the filter

    def __post_init__(self) -> None:
        if (
            any(self.roi_size % t for t in self.pyramid_T)
            or (self.roi_size // 2) % self.pyramid_T[1]
        ):
            raise ValueError(f"roi_size {self.roi_size} must be a multiple of T {self.pyramid_T}")
        if not 0 < self.fill <= 1 or self.focal <= 0 or self.inplane_step_deg <= 0:
            raise ValueError(f"invalid template config {self}")

    def canonical_depth(self, diameter: float) -> float:
        """z_r: metres at which the diameter spans ``fill * roi_size`` pixels."""
        return self.focal * diameter / (self.fill * self.roi_size)

    def camera(self) -> Camera:
        c = (self.roi_size - 1) / 2.0  # the object origin projects to the RoI centre
        K = np.array([[self.focal, 0, c], [0, self.focal, c], [0, 0, 1.0]])
        return Camera(K, self.roi_size, self.roi_size)


def make_detector(config: TemplateConfig):
    modality = cv2.linemod.ColorGradient_create(
        config.weak_threshold, config.n_features, config.strong_threshold
    )
    return cv2.linemod.Detector([modality], list(config.pyramid_T))


@dataclass(frozen=True, eq=False)
class TemplateBank:
    """The templates of one object.

    R_cam_obj: (N, 3, 3) rotations of the templates; feat_x, feat_y: (N, F) int16 feature
    positions in the RoI (pixels, level 0); feat_label: (N, F) uint8 quantised orientation
    (0..7); feat_valid: (N, F) bool (templates may have fewer than F features);
    z_r: canonical depth (metres); config: the parameters; build_seconds: time it took.
    """

    obj_id: int
    R_cam_obj: np.ndarray
    feat_x: np.ndarray
    feat_y: np.ndarray
    feat_label: np.ndarray
    feat_valid: np.ndarray
    z_r: float
    config: TemplateConfig
    build_seconds: float = 0.0

    def __len__(self) -> int:
        return len(self.R_cam_obj)

    @property
    def nbytes(self) -> int:
        return sum(
            a.nbytes
            for a in (self.R_cam_obj, self.feat_x, self.feat_y, self.feat_label, self.feat_valid)
        )


def icosphere_directions(subdivisions: int) -> np.ndarray:
    """(V, 3) unit vectors: the vertices of a subdivided icosahedron."""
    return np.asarray(trimesh.creation.icosphere(subdivisions=subdivisions).vertices)


def look_at_rotation(view_dir_obj: np.ndarray) -> np.ndarray:
    """R_cam_obj of a camera on ``view_dir_obj`` (unit, object -> camera) looking at the origin.

    The camera's x axis is horizontal in the object frame (perpendicular to z_obj), except when
    looking along z_obj, where x is along x_obj.
    """
    z_cam = -np.asarray(view_dir_obj, dtype=np.float64)
    up = np.array([0.0, 0.0, 1.0])
    x_cam = np.cross(up, z_cam) if abs(z_cam[2]) < 0.999 else np.array([1.0, 0.0, 0.0])
    x_cam /= np.linalg.norm(x_cam)
    y_cam = np.cross(z_cam, x_cam)
    return np.stack([x_cam, y_cam, z_cam])  # rows: camera axes in the object frame


def template_rotations(config: TemplateConfig, symmetries: np.ndarray | None = None) -> np.ndarray:
    """(N, 3, 3) R_cam_obj of the templates, in the fundamental region of ``symmetries``.

    symmetries: (S, 4, 4) with the identity first (object frame), or None.
    """
    return _template_grid(config, symmetries)[0]


def _template_grid(config: TemplateConfig, symmetries: np.ndarray | None = None):
    """The kept templates as ``(R_cam_obj (N, 3, 3), view (N,) icosphere index, inplane (N,)
    radians)``: ``R = Rz(inplane) @ look_at_rotation(direction[view])``."""
    angles = np.deg2rad(np.arange(0.0, 360.0, config.inplane_step_deg))
    rotations, views, inplane = [], [], []
    for k, v in enumerate(icosphere_directions(config.subdivisions)):
        base = look_at_rotation(v)
        for a in angles:
            c, s = np.cos(a), np.sin(a)
            Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
            rotations.append(Rz @ base)
            views.append(k)
            inplane.append(a)
    R, views, inplane = np.array(rotations), np.array(views), np.array(inplane)
    if symmetries is None or len(symmetries) <= 1:
        return R, views, inplane
    S = symmetries[:, :3, :3]
    # angle of every symmetric equivalent R @ S_i to the identity; keep R when S_0 = I is best
    equivalents = np.einsum("nij,sjk->nsik", R, S)
    ang = rotation_angle(equivalents.reshape(-1, 3, 3)).reshape(len(R), len(S))
    keep = ang[:, 0] <= ang.min(axis=1) + 1e-9
    return R[keep], views[keep], inplane[keep]


def _cache_key(model: ObjectModel, config: TemplateConfig) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(model.mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(model.mesh.faces, dtype=np.int64).tobytes())
    h.update(np.ascontiguousarray(model.symmetries_discrete, dtype=np.float64).round(9).tobytes())
    h.update(repr([(c.axis, c.offset) for c in model.symmetries_continuous]).encode())
    h.update(json.dumps(asdict(config), sort_keys=True).encode())
    h.update(f"v{CACHE_VERSION}".encode())
    return h.hexdigest()[:24]


def _on_terminal() -> bool:
    return sys.stderr.isatty()


def _render_template_view(
    renderer: Renderer, camera: Camera, view_dir_obj: np.ndarray, z_r: float, inplane: float = 0.0
):
    """BGR image (H, W, 3) uint8 and mask (H, W) uint8 of the object seen from ``view_dir_obj``
    at the canonical depth, turned by ``inplane`` radians about the optical axis."""
    c, s = np.cos(inplane), np.sin(inplane)
    T_cam_obj = np.eye(4)
    T_cam_obj[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]) @ look_at_rotation(
        view_dir_obj
    )
    T_cam_obj[2, 3] = z_r
    T_world_cam = np.linalg.inv(T_cam_obj)  # the object frame is the world here
    lights = tuple(
        DirectionalLight(tuple(T_world_cam[:3, :3] @ np.asarray(d)), c)
        for d, c in TEMPLATE_LIGHTS_CAM
    )
    lighting = Lighting(lights, ambient=(0.15, 0.15, 0.15), background=(0.0, 0.0, 0.0))
    result = renderer.render(camera, T_world_cam, lighting, shadows=False)
    mask = (result.instance >= 0).astype(np.uint8) * 255
    return cv2.cvtColor(result.image, cv2.COLOR_RGB2BGR), mask


def default_cache_dir() -> Path:
    return Path(os.environ.get(CACHE_ENV, Path.home() / ".cache" / "posefuse")) / "templates"


def build_template_bank(
    model: ObjectModel,
    config: TemplateConfig | None = None,
    cache_dir: str | Path | None = None,
    show_progress: bool = True,
) -> TemplateBank:
    """Render and extract the templates of ``model`` (or load them from the cache)."""
    config = config or TemplateConfig()
    cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    path = cache_dir / f"obj_{model.obj_id:06d}_{_cache_key(model, config)}.npz"
    if path.is_file():
        try:
            with np.load(path) as data:
                return TemplateBank(
                    model.obj_id,
                    data["R"],
                    data["x"],
                    data["y"],
                    data["label"],
                    data["valid"],
                    float(data["z_r"]),
                    config,
                    float(data["seconds"]),
                )
        except (OSError, KeyError, ValueError):
            path.unlink(missing_ok=True)  # a damaged cache entry is rebuilt
    start = time.perf_counter()
    step = np.deg2rad(config.symmetry_step_deg)
    symmetries = model.symmetry_transforms(step) if model.is_symmetric else None
    rotations, views, inplane = _template_grid(config, symmetries)
    z_r = config.canonical_depth(model.diameter)
    camera = config.camera()
    renderer = Renderer([model.mesh], materials=[TEMPLATE_MATERIAL])
    detector = make_detector(config)
    F = config.n_features
    xs = np.zeros((len(rotations), F), np.int16)
    ys = np.zeros((len(rotations), F), np.int16)
    labels = np.zeros((len(rotations), F), np.uint8)
    valid = np.zeros((len(rotations), F), bool)
    kept = np.zeros(len(rotations), bool)
    directions = icosphere_directions(config.subdivisions)
    # A turn about the optical axis turns the image about the principal point, which is the RoI
    # centre: each viewpoint is rendered once (the ray casting is 90% of the time) and its
    # in-plane turns are image rotations, 36x fewer renders. The lights turn with the image
    # (they are fixed to the camera, the headlight on the axis), so shading is unchanged.
    # Where the symmetry filter leaves a viewpoint one or two turns, warping saves nothing: those
    # are rendered. So is every template of a part with a continuous symmetry (few, ~140): seen
    # along its axis, its turns are one appearance and rendered templates stay identical, while
    # warps turn the fill lights with the image and differ by shading alone; measured on the
    # held-out mixed bins, warping them took the chrome screw from 55% to 34% ADD-sym at 8 views.
    turns_per_view = np.bincount(views, minlength=len(directions))
    if model.symmetries_continuous:
        turns_per_view[:] = 0
    centre = (camera.K[0, 2], camera.K[1, 2])
    size = (camera.width, camera.height)
    base_view = -1
    for k in tqdm(
        range(len(rotations)),
        desc=f"templates {model.name}",
        unit="tpl",
        disable=not show_progress,
        mininterval=1.0 if _on_terminal() else 30.0,
    ):
        if turns_per_view[views[k]] <= 2:
            turned, turned_mask = _render_template_view(
                renderer, camera, directions[views[k]], z_r, inplane[k]
            )
        else:
            if views[k] != base_view:
                base_view = views[k]
                image, mask = _render_template_view(renderer, camera, directions[base_view], z_r)
            M = cv2.getRotationMatrix2D(centre, -np.degrees(inplane[k]), 1.0)
            turned = cv2.warpAffine(image, M, size, flags=cv2.INTER_LINEAR)
            turned_mask = cv2.warpAffine(mask, M, size, flags=cv2.INTER_NEAREST)
        tid, bbox = detector.addTemplate([turned], "t", turned_mask)
        if tid < 0:
            continue  # too few gradient features (an edge-on thin part)
        features = detector.getTemplates("t", tid)[0].features
        n = min(len(features), F)
        xs[k, :n] = [bbox[0] + f.x for f in features[:n]]
        ys[k, :n] = [bbox[1] + f.y for f in features[:n]]
        labels[k, :n] = [f.label for f in features[:n]]
        valid[k, :n] = True
        kept[k] = True
    seconds = time.perf_counter() - start
    bank = TemplateBank(
        model.obj_id,
        rotations[kept],
        xs[kept],
        ys[kept],
        labels[kept],
        valid[kept],
        z_r,
        config,
        seconds,
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(
        tmp,
        R=bank.R_cam_obj,
        x=bank.feat_x,
        y=bank.feat_y,
        label=bank.feat_label,
        valid=bank.feat_valid,
        z_r=z_r,
        seconds=seconds,
    )
    tmp.replace(path)
    return bank


def _build_quietly(args) -> TemplateBank:
    model, config, cache_dir = args
    return build_template_bank(model, config, cache_dir, show_progress=False)


def build_template_banks(
    models: list[ObjectModel],
    config: TemplateConfig | None = None,
    cache_dir: str | Path | None = None,
    workers: int = 2,
    progress=None,
) -> dict[int, TemplateBank]:
    """The banks of several objects by obj_id: cached ones loaded, the others built in
    ``workers`` processes (one object each). ``progress(name, seconds, cached)`` is called as
    each bank is ready, in the order of ``models``."""
    from concurrent.futures import ProcessPoolExecutor

    config = config or TemplateConfig()
    cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    missing = [
        m
        for m in models
        if not (cache_dir / f"obj_{m.obj_id:06d}_{_cache_key(m, config)}.npz").is_file()
    ]
    built: dict[int, TemplateBank] = {}
    if len(missing) > 1 and workers > 1:
        with ProcessPoolExecutor(min(workers, len(missing))) as pool:
            jobs = [(m, config, cache_dir) for m in missing]
            for m, bank in zip(missing, pool.map(_build_quietly, jobs), strict=True):
                built[m.obj_id] = bank
    out = {}
    for m in models:
        start = time.perf_counter()
        bank = built.get(m.obj_id) or build_template_bank(m, config, cache_dir, show_progress=False)
        out[m.obj_id] = bank
        if progress is not None:
            cached = m not in missing
            progress(m.name, time.perf_counter() - start if cached else bank.build_seconds, cached)
    return out
