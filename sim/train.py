"""Training the center-voting front end on synthetic renders (CPU, torch), export to ONNX.

``posefuse train --catalog DIR --out models/NAME.onnx`` renders bin scenes of the catalog with
:mod:`sim` (scene seeds from ``TRAIN_SEED_BASE`` on, disjoint from the test sets' seeds; random
lighting, bin textures, piles with occlusion, sensor noise; half of the scenes in the robi
profile) at 1280x720 and resizes them to the network's input scale as the front end does;
trains :class:`sim.net.CenterVotingNet` on crops (most of them centred on a part) with
brightness, contrast and noise augmentation; calibrates the voting covariance on held-out
renders made the same way; exports ONNX (opset 17) and writes the model card beside it.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from estimator.camera import Camera
from estimator.frontend.network import MEAN, STD, ModelCard, catalog_hash, output_to_image
from estimator.frontend.voting import VotingConfig, vote_instances
from estimator.objects import Catalog, load_catalog
from estimator.render import CHROME, METAL, Renderer
from sim.scenes import PROFILES, REALSENSE_1280x720, make_scene
from sim.sensor import SensorModel, apply_rgb
from sim.synth import BIN_ID, scene_seed

TRAIN_SEED_BASE = 7_000_000  # scene seeds of training data; test sets use small seeds
INPUT_SCALE = 0.5
OUTPUT_STRIDE = 2


@dataclass(frozen=True)
class TrainConfig:
    n_scenes: int = 400
    views_per_scene: int = 4
    val_scenes: int = 12
    minutes: float = 40.0
    max_iterations: int = 100_000
    batch: int = 8
    crop: tuple[int, int] = (256, 320)  # input pixels (height, width)
    lr: float = 2e-3
    width: int = 16
    seed: int = 0
    workers: int = 2
    robi_fraction: float = 0.5  # of the scenes rendered with the robi profile, the rest mixed
    deadline: float | None = None  # wall-clock time (time.time()) the training loop must end by


def _class_index(catalog: Catalog) -> dict[int, int]:
    return {obj_id: k + 1 for k, obj_id in enumerate(sorted(catalog))}


def profile_of(scene_index: int, robi_fraction: float) -> str:
    """Which profile a training scene uses: ``robi_fraction`` of them, interleaved, are robi."""
    robi = int((scene_index + 1) * robi_fraction) > int(scene_index * robi_fraction)
    return "robi" if robi else "mixed"


_CATALOGS: dict[str, Catalog] = {}


def _cached_catalog(catalog_dir: str) -> Catalog:
    """One load per rendering process (a worker renders many scenes of the same catalog)."""
    if catalog_dir not in _CATALOGS:
        _CATALOGS[catalog_dir] = load_catalog(catalog_dir)
    return _CATALOGS[catalog_dir]


def render_views(args: tuple) -> list[tuple]:
    """One scene's views as (image (Hp, W, 3) uint8, labels (h, w) uint8, vectors (2, h, w)
    float16, centers (K, 3) class and output-grid x, y), at the network's input scale; the
    picklable unit of parallel rendering.

    Views are made exactly as test images and the service's frames are: rendered at 1280x720
    with the sensor model applied there, then resized by ``INPUT_SCALE`` with the same
    ``cv2.resize`` as the front end's pre-processing (the instance map by nearest neighbour).
    """
    catalog_dir, scene_index, views, seed_base, profile = args
    catalog = _cached_catalog(catalog_dir)
    classes = _class_index(catalog)
    seed = scene_seed(seed_base, scene_index)
    full = REALSENSE_1280x720
    camera = full.scaled(INPUT_SCALE)
    spec = dataclasses.replace(PROFILES[profile], n_views=views)
    scene = make_scene(catalog, spec, seed, full)
    materials = [CHROME if "screw" in catalog[i.obj_id].name else METAL for i in scene.instances]
    meshes = [catalog[i.obj_id].mesh for i in scene.instances] + [scene.bin_mesh]
    poses = [i.T_world_obj for i in scene.instances] + [np.eye(4)]
    ids = list(range(len(scene.instances))) + [BIN_ID]
    renderer = Renderer(meshes, poses, ids, materials + [scene.bin_material])
    rng = np.random.default_rng(seed + 1)
    size = (camera.width, camera.height)
    out = []
    for T_world_cam in scene.T_world_cams:
        res = renderer.render(full, T_world_cam, scene.lighting)
        image = cv2.resize(
            apply_rgb(res.image, SensorModel(), rng), size, interpolation=cv2.INTER_AREA
        )
        instance = cv2.resize(res.instance.astype(np.int32), size, interpolation=cv2.INTER_NEAREST)
        out.append(make_targets(image, instance, scene, T_world_cam, camera, classes))
    return out


def make_targets(image, instance, scene, T_world_cam, camera: Camera, classes):
    """Pad to a multiple of 16; labels and unit vectors on the output grid."""
    H, W = instance.shape
    Hp = H + (-H % 16)
    img = np.concatenate([image, np.repeat(image[-1:], Hp - H, axis=0)], 0)
    inst = np.concatenate([instance, np.full((Hp - H, W), -1, instance.dtype)], 0)
    h, w = Hp // OUTPUT_STRIDE, W // OUTPUT_STRIDE
    grid = inst[::OUTPUT_STRIDE, ::OUTPUT_STRIDE]  # (h, w)
    labels = np.zeros((h, w), np.uint8)
    vectors = np.zeros((2, h, w), np.float16)
    T_cam_world = np.linalg.inv(T_world_cam)
    ys, xs = np.mgrid[0:h, 0:w]
    px = xs * OUTPUT_STRIDE + 0.5 * (OUTPUT_STRIDE - 1)  # output pixel centres, input coords
    py = ys * OUTPUT_STRIDE + 0.5 * (OUTPUT_STRIDE - 1)
    centers = []  # (class, x, y) on the output grid, per visible instance
    for k, inst_k in enumerate(scene.instances):
        sel = grid == k
        if not sel.any():
            continue
        t_cam = T_cam_world[:3, :3] @ inst_k.T_world_obj[:3, 3] + T_cam_world[:3, 3]
        u, v = camera.project(t_cam)
        dx, dy = u - px[sel], v - py[sel]
        n = np.maximum(np.hypot(dx, dy), 1e-6)
        labels[sel] = classes[inst_k.obj_id]
        vectors[0][sel] = dx / n
        vectors[1][sel] = dy / n
        s = OUTPUT_STRIDE
        centers.append((classes[inst_k.obj_id], (u - 0.5 * (s - 1)) / s, (v - 0.5 * (s - 1)) / s))
    return img, labels, vectors, np.array(centers).reshape(-1, 3)


def render_dataset(catalog_dir, n_scenes, views, seed_base, workers, desc, robi_fraction=0.0):
    jobs = [
        (str(catalog_dir), k, views, seed_base, profile_of(k, robi_fraction))
        for k in range(n_scenes)
    ]
    items = []
    with tqdm(total=n_scenes, desc=desc, unit="scene") as bar:
        if workers > 1:
            with get_context("spawn").Pool(workers) as pool:
                for views_out in pool.imap(render_views, jobs):
                    items.extend(views_out)
                    bar.update(1)
        else:
            for job in jobs:
                items.extend(render_views(job))
                bar.update(1)
    images = np.stack([it[0] for it in items])
    labels = np.stack([it[1] for it in items])
    vectors = np.stack([it[2] for it in items])
    return images, labels, vectors, [it[3] for it in items]


def crop_origins(
    image_hw: tuple[int, int],
    crop_hw: tuple[int, int],
    centers: list[np.ndarray],
    rng: np.random.Generator,
    on_part: float = 0.8,
) -> tuple[np.ndarray, np.ndarray]:
    """Top-left corners (y0, x0), multiples of 16, of one crop per image: with probability
    ``on_part`` the crop holds a random visible instance's center (parts fill a small share of
    a bin view; crops of empty bin floor teach little), otherwise anywhere.

    Args:
        centers: per image (K, 3) class and output-grid x, y of its visible instances.
    Returns:
        y0, x0: (B,) each.
    """
    H, W = image_hw
    ch, cw = crop_hw
    ny, nx = (H - ch) // 16 + 1, (W - cw) // 16 + 1
    y0 = rng.integers(0, ny, size=len(centers)) * 16
    x0 = rng.integers(0, nx, size=len(centers)) * 16
    for b, c in enumerate(centers):
        if len(c) == 0 or rng.random() >= on_part:
            continue
        _, cx, cy = c[rng.integers(len(c))]
        px, py = cx * OUTPUT_STRIDE, cy * OUTPUT_STRIDE  # input pixels
        # corners whose crop keeps the center at least 32 px from its border
        lo_x, hi_x = int(np.ceil((px + 32 - cw) / 16)), int(np.floor((px - 32) / 16))
        lo_y, hi_y = int(np.ceil((py + 32 - ch) / 16)), int(np.floor((py - 32) / 16))
        lo_x, hi_x = max(lo_x, 0), min(hi_x, nx - 1)
        lo_y, hi_y = max(lo_y, 0), min(hi_y, ny - 1)
        if lo_x <= hi_x:
            x0[b] = rng.integers(lo_x, hi_x + 1) * 16
        if lo_y <= hi_y:
            y0[b] = rng.integers(lo_y, hi_y + 1) * 16
    return y0, x0


def _normalise(images_uint8):
    import torch

    x = torch.from_numpy(images_uint8).float().div_(255.0)
    x = (x - torch.tensor(MEAN)) / torch.tensor(STD)
    return x.permute(0, 3, 1, 2).contiguous()


def train(catalog_dir: str | Path, model_path: str | Path, config: TrainConfig) -> dict:
    """Render, train, calibrate, export; returns the model card's dict."""
    import torch
    from torch.nn import functional as F

    from sim.net import CenterVotingNet

    torch.manual_seed(config.seed)
    torch.set_num_threads(2)
    catalog = load_catalog(catalog_dir)
    n_classes = len(catalog)
    start = time.time()
    images, labels, vectors, centers = render_dataset(
        catalog_dir,
        config.n_scenes,
        config.views_per_scene,
        TRAIN_SEED_BASE,
        config.workers,
        "render train",
        config.robi_fraction,
    )
    val = render_dataset(
        catalog_dir,
        config.val_scenes,
        config.views_per_scene,
        TRAIN_SEED_BASE + 1,
        config.workers,
        "render val",
        config.robi_fraction,
    )
    render_minutes = (time.time() - start) / 60
    model = CenterVotingNet(n_classes, config.width)
    opt = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=1e-4)
    rng = np.random.default_rng(config.seed)
    fg = (labels > 0).mean()
    class_w = torch.ones(n_classes + 1)
    class_w[0] = float(np.clip(fg / (1 - fg) * 4, 0.05, 1.0))  # background is most pixels
    ch, cw = config.crop
    loop_start = time.time()
    deadline = loop_start + config.minutes * 60
    if config.deadline is not None:
        deadline = min(deadline, config.deadline)
    it = 0
    # the budget is time: the bar counts seconds, so its ETA is the end of training
    bar = tqdm(total=max(int(deadline - loop_start), 1), desc="train", unit="s")
    losses = []
    model.train()
    while it < config.max_iterations and time.time() < deadline:
        frac = min((time.time() - loop_start) / max(deadline - loop_start, 1e-9), 1)
        for g in opt.param_groups:
            g["lr"] = config.lr * 0.5 * (1 + np.cos(np.pi * frac))
        idx = rng.integers(len(images), size=config.batch)
        y0, x0 = crop_origins(images.shape[1:3], config.crop, [centers[i] for i in idx], rng)
        xb = np.stack(
            [images[i, a : a + ch, b : b + cw] for i, a, b in zip(idx, y0, x0, strict=True)]
        )
        s = OUTPUT_STRIDE
        lb = np.stack(
            [
                labels[i, a // s : (a + ch) // s, b // s : (b + cw) // s]
                for i, a, b in zip(idx, y0, x0, strict=True)
            ]
        )
        vb = np.stack(
            [
                vectors[i, :, a // s : (a + ch) // s, b // s : (b + cw) // s]
                for i, a, b in zip(idx, y0, x0, strict=True)
            ]
        )
        x = _normalise(xb)
        gain = torch.from_numpy(rng.uniform(0.7, 1.3, (config.batch, 1, 1, 1))).float()
        bias = torch.from_numpy(rng.uniform(-0.3, 0.3, (config.batch, 1, 1, 1))).float()
        x = x * gain + bias + 0.05 * torch.randn_like(x)
        out = model(x)
        target = torch.from_numpy(lb.astype(np.int64))
        loss_cls = F.cross_entropy(out[:, : n_classes + 1], target, weight=class_w)
        mask = (target > 0).unsqueeze(1).float()
        vt = torch.from_numpy(vb.astype(np.float32))
        loss_vec = (F.smooth_l1_loss(out[:, n_classes + 1 :], vt, reduction="none") * mask).sum()
        loss_vec = loss_vec / mask.sum().clamp(min=1)
        loss = loss_cls + 2.0 * loss_vec
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
        it += 1
        if it % 20 == 0:
            bar.set_postfix(it=it, loss=f"{np.mean(losses[-20:]):.3f}", refresh=False)
            bar.update(
                min(int(time.time() - loop_start), bar.total) - bar.n
            )  # respects mininterval
    bar.close()
    train_minutes = (time.time() - start) / 60 - render_minutes
    model.eval()
    model_path = Path(model_path)
    model_path.parent.mkdir(parents=True, exist_ok=True)
    dummy = torch.zeros(1, 3, 368, 640)
    torch.onnx.export(
        model,
        (dummy,),
        str(model_path),
        dynamo=False,
        opset_version=17,
        input_names=["image"],
        output_names=["out"],
        dynamic_axes={"image": {2: "h", 3: "w"}, "out": {2: "h2", 3: "w2"}},
    )
    card = ModelCard(
        classes=tuple((k, m.name) for k, m in sorted(catalog.items())),
        catalog_hash=catalog_hash(catalog),
        image_size=(REALSENSE_1280x720.width, REALSENSE_1280x720.height),
        input_scale=INPUT_SCALE,
        output_stride=OUTPUT_STRIDE,
    )
    cov_scale, val_metrics = calibrate(model, val, card, n_classes)
    card = ModelCard(
        card.classes,
        card.catalog_hash,
        card.image_size,
        card.input_scale,
        card.output_stride,
        cov_scale=cov_scale,
        extra={
            "architecture": f"CenterVotingNet(width={config.width}), "
            f"{sum(p.numel() for p in model.parameters())} parameters",
            "training": {
                "data": f"{config.n_scenes} scenes x {config.views_per_scene} views "
                f"({config.robi_fraction:.0%} robi profile, the rest mixed), rendered at "
                f"1280x720 and resized to {int(1280 * INPUT_SCALE)}x{int(720 * INPUT_SCALE)} "
                f"as the front end does, scene seeds scene_seed({TRAIN_SEED_BASE}, "
                f"0..{config.n_scenes - 1}); validation scene_seed({TRAIN_SEED_BASE + 1}, "
                f"0..{config.val_scenes - 1})",
                "iterations": it,
                "batch": config.batch,
                "crop": list(config.crop),
                "crops_on_a_part": 0.8,
                "final_loss": float(np.mean(losses[-100:])) if losses else None,
                "render_minutes": round(render_minutes, 1),
                "train_minutes": round(train_minutes, 1),
                "seed": config.seed,
            },
            "validation": val_metrics,
        },
    )
    model_path.with_suffix(".json").write_text(json.dumps(card.to_json(), indent=2) + "\n")
    return card.to_json()


def calibrate(model, val, card: ModelCard, n_classes: int) -> tuple[float, dict]:
    """Run the voting on held-out renders: the covariance scale that makes the mean NEES of the
    2D center equal 2 (its expectation), and validation metrics."""
    import torch

    images, _, _, centers = val
    nees, errors = [], []
    n_true = n_found = 0
    with torch.no_grad():
        for k in range(len(images)):
            out = model(_normalise(images[k : k + 1]))[0].numpy()
            pred = np.argmax(out[: n_classes + 1], 0)
            h, w = pred.shape
            ys, xs = np.mgrid[0:h, 0:w]
            n_true += len(centers[k])
            for c in range(1, n_classes + 1):
                sel = pred == c
                truth = centers[k][centers[k][:, 0] == c, 1:]
                if sel.sum() < 25 or len(truth) == 0:
                    continue
                pix = np.stack([xs[sel], ys[sel]], 1).astype(float)
                vec = out[n_classes + 1 :, sel].T.astype(float)
                for inst in vote_instances(pix, vec, VotingConfig(), k):
                    d = np.linalg.norm(truth - inst.center, axis=1)
                    j = int(np.argmin(d))
                    if d[j] > 5.0:  # output pixels
                        continue
                    n_found += 1
                    e = inst.center - truth[j]
                    errors.append(
                        np.linalg.norm(
                            output_to_image(inst.center, card) - output_to_image(truth[j], card)
                        )
                    )
                    nees.append(e @ np.linalg.solve(inst.cov, e))
    nees = np.array(nees)
    scale = float(np.mean(nees) / 2.0) if len(nees) else 1.0
    return scale, {
        "views": int(len(images)),
        "visible_instances": int(n_true),
        "found_within_5_output_px": int(n_found),
        "median_center_error_px_full_res": float(np.median(errors)) if errors else None,
        "mean_nees_before_calibration": float(np.mean(nees)) if len(nees) else None,
    }
