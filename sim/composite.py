"""Training views composed from parts rendered alone: many views a minute, of any part's any pose.

A training scene rendered whole (``sim.train_data``) lays its parts out (dropped one by one onto
a pile, ray-cast as they fall) and ray-casts every pixel of every view: 19 s a scene of 6 views
for LM-O's eight household meshes on 2 cores, so a 15-minute onboarding sees 30 views of them.
A composed scene instead renders each part alone, in a random orientation, into a crop just
large enough for it (:func:`part_cutout`: tens of milliseconds), and pastes cut-outs onto
procedural clutter (``sim.backgrounds``), turned about the line of sight and scaled as a camera
turned and moved would see them, one over another as they would hide each other
(:func:`compose_view`). Its labels follow exactly: each instance's visible pixels, its visible
box and fraction, and the projection of its origin.

What a composed view lacks: contact, shadows and light bouncing between parts, a bin's walls;
the rendered scenes keep those (``RenderSpec.composite`` sets the share of each). What it adds:
every orientation of every part, not only those a part comes to rest in, on backgrounds as
varied as a real cell's (Dwibedi et al., "Cut, Paste and Learn", ICCV 2017).

A composed scene is the same unit as a rendered one (``views`` views from one seed), so the
training set's files, resumption and parallel rendering are unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from posefuse.estimator.core.camera import Camera
from posefuse.estimator.rotation.render import Renderer, random_lighting
from posefuse.sim.backgrounds import Backgrounds, clutter
from posefuse.sim.sensor import SensorModel, apply_rgb

__all__ = ["Cutout", "ComposeSpec", "compose_view", "part_cutout"]


@dataclass(frozen=True)
class Cutout:
    """A part rendered alone: rgb (S, S, 3) uint8, alpha (S, S) bool where the part shows,
    centre (2,) the projection of its origin in the crop's pixels, and its class index."""

    rgb: np.ndarray
    alpha: np.ndarray
    centre: np.ndarray
    class_index: int


@dataclass(frozen=True)
class ComposeSpec:
    """How a composed scene is drawn."""

    cutouts: int = 16  # parts rendered alone per scene, shared by its views
    distance: tuple[float, float] = (0.45, 1.1)  # metres, camera to part
    mixed_parts: tuple[int, int] = (3, 12)  # per view, spread over the image
    pile_parts: tuple[int, int] = (12, 30)  # per view, heaped into a region
    turn: bool = True  # cut-outs turned about the line of sight (a camera's roll)
    scale_log: float = 0.15  # and scaled by exp(U(-s, s)) (a camera a little nearer or farther)


def part_cutout(
    mesh, material, class_index: int, focal_px: float, rng: np.random.Generator, spec: ComposeSpec
) -> Cutout:
    """One part, uniformly random orientation, at a random distance, lit by random lights from
    above the camera, rendered into the smallest square crop that holds it."""
    R = Rotation.random(random_state=int(rng.integers(2**31))).as_matrix()
    z = float(rng.uniform(*spec.distance))
    radius = float(np.linalg.norm(mesh.vertices, axis=1).max())  # about the origin
    size = int(np.ceil(2.1 * focal_px * radius / max(z - radius, 0.05)))
    size = int(np.clip(size + size % 2, 16, 720))
    c = (size - 1) / 2.0
    camera = Camera(np.array([[focal_px, 0, c], [0, focal_px, c], [0, 0, 1.0]]), size, size)
    # the camera above the part, looking down (world z up, as the lights are placed)
    T_world_cam = np.eye(4)
    T_world_cam[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T_world_cam[2, 3] = z
    T_world_obj = np.eye(4)
    T_world_obj[:3, :3] = R
    renderer = Renderer([mesh], [T_world_obj], [0], [material])
    result = renderer.render(camera, T_world_cam, random_lighting(int(rng.integers(2**31))))
    return Cutout(result.image, result.instance == 0, np.array([c, c]), int(class_index))


def _transformed(cut: Cutout, angle: float, scale: float) -> Cutout:
    """The cut-out turned by ``angle`` (radians) about its centre and scaled, into a crop large
    enough for it."""
    S = cut.rgb.shape[0]
    size = int(np.clip(np.ceil(S * scale * 1.42), 8, 1440))
    size += size % 2
    M = cv2.getRotationMatrix2D(
        (float(cut.centre[0]), float(cut.centre[1])), np.rad2deg(angle), scale
    )
    new_c = (size - 1) / 2.0
    M[:, 2] += new_c - cut.centre
    rgb = cv2.warpAffine(cut.rgb, M, (size, size), flags=cv2.INTER_LINEAR)
    alpha = cv2.warpAffine(
        cut.alpha.astype(np.uint8) * 255, M, (size, size), flags=cv2.INTER_LINEAR
    )
    return Cutout(rgb, alpha >= 128, np.array([new_c, new_c]), cut.class_index)


def compose_view(
    cutouts: list[Cutout],
    pile: bool,
    height: int,
    width: int,
    rng: np.random.Generator,
    spec: ComposeSpec,
    backgrounds: Backgrounds | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One composed view.

    Returns:
        rgb: (H, W, 3) uint8 with the sensor's blur and noise (``sim.sensor``); inst: (H, W)
        uint8, k + 1 where instance k shows, 0 elsewhere; rows: (K, 10) the instance rows of
        ``sim.train_data.INSTANCE_COLUMNS`` but the view (instance, class, u, v, visible box,
        visible fraction, visible pixels) of the instances that show.
    """
    lo, hi = spec.pile_parts if pile else spec.mixed_parts
    n = int(rng.integers(lo, hi + 1))
    canvas = clutter(height, width, rng, backgrounds or Backgrounds()).astype(np.float32)
    inst = np.zeros((height, width), np.uint8)
    placed = []  # (class, u, v, full pixel count)
    if pile:  # heaped: centres within a region a fifth to half of the image across
        half = rng.uniform(0.1, 0.25, 2) * np.array([width, height])
        middle = rng.uniform(half, np.array([width, height]) - half)
    for k in range(min(n, 254)):
        cut = cutouts[int(rng.integers(len(cutouts)))]
        angle = rng.uniform(-np.pi, np.pi) if spec.turn else 0.0
        cut = _transformed(cut, angle, float(np.exp(rng.uniform(-1, 1) * spec.scale_log)))
        if pile:
            uv = middle + rng.uniform(-1, 1, 2) * half
        else:
            uv = rng.uniform([0, 0], [width, height])
        x0 = int(round(uv[0] - cut.centre[0]))
        y0 = int(round(uv[1] - cut.centre[1]))
        S = cut.rgb.shape[0]
        # the part of the crop inside the image
        cx0, cy0 = max(0, -x0), max(0, -y0)
        cx1, cy1 = min(S, width - x0), min(S, height - y0)
        if cx1 <= cx0 or cy1 <= cy0:
            continue
        a = cut.alpha[cy0:cy1, cx0:cx1]
        region = (slice(y0 + cy0, y0 + cy1), slice(x0 + cx0, x0 + cx1))
        canvas[region][a] = cut.rgb[cy0:cy1, cx0:cx1][a]
        inst[region][a] = k + 1
        # in the image, as a render's visible fraction counts it
        placed.append((k, cut.class_index, x0 + cut.centre[0], y0 + cut.centre[1], a.sum()))
    rgb = apply_rgb(np.clip(canvas + 0.5, 0, 255).astype(np.uint8), SensorModel(), rng)
    rows = []
    for k, cls, u, v, full in placed:
        ys, xs = np.nonzero(inst == k + 1)
        if len(xs) == 0 or full == 0:
            continue
        visib = min(len(xs) / full, 1.0)
        rows.append((k, cls, u, v, xs.min(), ys.min(), xs.max() + 1, ys.max() + 1, visib, len(xs)))
    return rgb, inst, np.array(rows, np.float64).reshape(-1, 10)
