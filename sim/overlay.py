"""Pictures of a BOP view with poses drawn over it: visible-mask outlines, model axes, labels."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from posefuse.estimator.core.camera import Camera


def _colour(k: int) -> tuple[int, int, int]:
    hue = (k * 47) % 180
    hsv = np.uint8([[[hue, 220, 255]]])
    b, g, r = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0]
    return int(b), int(g), int(r)


def draw_pose(
    image_bgr: np.ndarray,
    camera: Camera,
    T_cam_obj: np.ndarray,
    points_obj: np.ndarray,
    axis_length: float,
    colour: tuple[int, int, int],
    label: str | None = None,
) -> None:
    """Draw projected model points, the object's axes (x red, y green, z blue) and a label.

    Args:
        image_bgr: (H, W, 3) uint8, drawn on in place.
        T_cam_obj: (4, 4) metres. points_obj: (N, 3) model surface samples, metres.
    """
    pts_cam = points_obj @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    front = pts_cam[:, 2] > 1e-3
    uv = camera.project(pts_cam[front])
    h, w = image_bgr.shape[:2]
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    for u, v in uv[inside].astype(int):
        image_bgr[v, u] = colour
    origin = T_cam_obj[:3, 3]
    if origin[2] <= 1e-3:
        return
    axes = origin[:, None] + T_cam_obj[:3, :3] * axis_length  # (3, 3): one axis tip per column
    o = camera.project(origin)
    for k, c in enumerate(((0, 0, 255), (0, 200, 0), (255, 80, 0))):
        tip = camera.project(axes[:, k])
        cv2.line(
            image_bgr,
            tuple(np.round(o).astype(int)),
            tuple(np.round(tip).astype(int)),
            c,
            2,
            cv2.LINE_AA,
        )
    cv2.circle(image_bgr, tuple(np.round(o).astype(int)), 3, (255, 255, 255), -1, cv2.LINE_AA)
    if label:
        cv2.putText(
            image_bgr,
            label,
            tuple(np.round(o).astype(int) + [6, -6]),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.45,
            (255, 255, 255),
            1,
            cv2.LINE_AA,
        )


def gt_overlay(dataset, scene_id: int, im_id: int) -> np.ndarray:
    """(H, W, 3) BGR image of one view with every ground-truth instance drawn."""
    scene = dataset.scene(scene_id)
    view = scene.view(im_id)
    image = cv2.cvtColor(scene.load_rgb(im_id), cv2.COLOR_RGB2BGR)
    for gt in view.gts:
        colour = _colour(gt.gt_idx)
        mask = scene.load_mask_visib(im_id, gt.gt_idx).astype(np.uint8)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(image, contours, -1, colour, 1, cv2.LINE_AA)
        if gt.visib_fract <= 0:
            continue
        model = dataset.catalog[gt.obj_id]
        draw_pose(
            image,
            view.camera,
            gt.T_cam_obj,
            model.points[::4],
            model.diameter * 0.35,
            colour,
            f"{model.name} {gt.visib_fract:.2f}",
        )
    return image


def write_gt_overlay(dataset, scene_id: int, im_id: int, out: str | Path) -> Path:
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), gt_overlay(dataset, scene_id, im_id))
    return out


def frontend_overlay(
    image_rgb: np.ndarray,
    raw_output: np.ndarray,
    detections,
    card,
    true_centers: np.ndarray | None = None,
    arrow_step: int = 6,
) -> np.ndarray:
    """(H, W, 3) BGR picture of the learned front end on one image: predicted class masks
    (tinted), the vector field (short arrows every ``arrow_step`` output pixels), the voted
    centers with their 3-sigma ellipses (white) and the true centers (green crosses).

    raw_output: (C + 3, h, w) network output; detections: list of Detection; card: ModelCard.
    """
    from posefuse.estimator.frontend.network import output_to_image

    if getattr(card, "kind", "center_voting") == "two_stage":
        return _two_stage_overlay(image_rgb, detections, card, true_centers)
    image = cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR).copy()
    H, W = image.shape[:2]
    n_classes = len(card.classes)
    labels = np.argmax(raw_output[: n_classes + 1], axis=0)
    vectors = raw_output[n_classes + 1 :]
    big = cv2.resize(
        labels.astype(np.uint8),
        None,
        fx=card.output_stride / card.input_scale,
        fy=card.output_stride / card.input_scale,
        interpolation=cv2.INTER_NEAREST,
    )
    big = big[:H, :W]
    tint = image.copy()
    for c in range(1, n_classes + 1):
        tint[big == c] = _colour(c * 3)
    image = cv2.addWeighted(image, 0.55, tint, 0.45, 0)
    h, w = labels.shape
    for y in range(0, h, arrow_step):
        for x in range(0, w, arrow_step):
            if labels[y, x] == 0:
                continue
            p = output_to_image(np.array([x, y], float), card)
            q = p + vectors[:, y, x] * 10
            cv2.arrowedLine(
                image,
                tuple(np.round(p).astype(int)),
                tuple(np.round(q).astype(int)),
                (255, 255, 255),
                1,
                cv2.LINE_AA,
                tipLength=0.4,
            )
    _draw_centers(image, detections, true_centers)
    return image


def _two_stage_overlay(image_rgb, detections, card, true_centers) -> np.ndarray:
    """Each detection's mask tinted by class, its box, its voted center with the 3-sigma
    ellipse (white), and the true centers (green crosses)."""
    image = cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR).copy()
    tint = image.copy()
    order = {obj_id: k + 1 for k, (obj_id, _) in enumerate(card.classes)}
    for d in detections:
        if d.mask is not None:
            tint[d.mask] = _colour(order.get(d.obj_id, 0) * 3)
    image = cv2.addWeighted(image, 0.55, tint, 0.45, 0)
    for d in detections:
        x, y, w, h = np.round(d.bbox_xywh).astype(int)
        cv2.rectangle(image, (x, y), (x + w, y + h), _colour(order.get(d.obj_id, 0) * 3), 1)
    _draw_centers(image, detections, true_centers)
    return image


def _draw_centers(image: np.ndarray, detections, true_centers=None) -> None:
    """True centers (green crosses), then the voted ones (red) with their 3-sigma ellipses."""
    if true_centers is not None:
        for u, v in true_centers:
            cv2.drawMarker(
                image, (int(round(u)), int(round(v))), (0, 255, 0), cv2.MARKER_CROSS, 14, 2
            )
    for d in detections:
        evals, evecs = np.linalg.eigh(d.center_cov)
        axes = tuple(int(max(1, round(3 * np.sqrt(e)))) for e in evals)
        angle = float(np.degrees(np.arctan2(evecs[1, 0], evecs[0, 0])))
        c = tuple(np.round(d.center_uv).astype(int))
        cv2.ellipse(image, c, axes, angle, 0, 360, (255, 255, 255), 1, cv2.LINE_AA)
        cv2.circle(image, c, 3, (0, 0, 255), -1, cv2.LINE_AA)
