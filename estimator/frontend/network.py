"""The learned front end: an ONNX center-voting network run with onnxruntime, then voting.

A model ``NAME.onnx`` comes with its card ``NAME.json``: the classes (obj_id and name, in
output order), a hash of the catalog it was trained for, the image size it expects, the input
scale and normalisation, the output stride, the calibrated covariance scale of the voting, and
how it was trained and measured. A model whose classes do not match the catalog is refused.

Per image: resize by ``input_scale``, pad to a multiple of 16, normalise, run the network,
label each output pixel with its most likely class, and vote for centers per class
(:mod:`estimator.frontend.voting`). Centers, covariances, masks and boxes are returned in the
image's own pixels.
"""

from __future__ import annotations

import dataclasses
import zlib
from pathlib import Path

import cv2
import numpy as np

from posefuse.estimator.core.errors import PosefuseError
from posefuse.estimator.frontend.card import (  # noqa: F401  (the card's names, re-exported)
    AGNOSTIC_CLASSES,
    CARD_VERIFICATION_KEYS,
    MEAN,
    STD,
    ModelCard,
    ModelError,
    card_verification,
    catalog_hash,
    class_scale_factors,
    load_card,
    score_factor,
)
from posefuse.estimator.frontend.detection import Detection, ExpectedPart
from posefuse.estimator.frontend.two_stage import (
    Box,
    CropVote,
    TwoStageConfig,
    box_masks,
    crop_boxes,
    crop_side,
    decode_boxes,
    detection_of,
    suppress_duplicates,
    vote_center,
)
from posefuse.estimator.frontend.voting import VotingConfig, compile_kernels, vote_instances


class UnsupportedImage(PosefuseError, ValueError):
    """An image the front end cannot take (wrong type, channels, or size); ``reason`` says
    which, in a form fit for a counter."""

    def __init__(self, reason: str, message: str):
        self.reason = reason
        super().__init__(message)


MIN_IMAGE_SIDE = 32  # pixels: smaller images hold no part a camera could be asked about


def image_seed(image: np.ndarray) -> int:
    """A seed of an image's pixels (CRC-32 of its shape and bytes, 0.2 ms for 640x480 RGB):
    (H, W, 3) uint8 -> int in [0, 2**32)."""
    pixels = np.ascontiguousarray(image)
    return zlib.crc32(pixels, zlib.crc32(repr(pixels.shape).encode()))


def input_scale_for(image_hw: tuple[int, int], card: ModelCard) -> float:
    """Network input pixels per image pixel for an image of this size.

    A one-stage model takes its own image size only (``card.input_scale``). The two-stage
    detector sees every image at the width it was trained at (640 px for 1280x720 at 0.5),
    whatever the sensor's resolution or aspect; stage two crops from the image itself, so
    centers, masks and covariances come back in the image's own pixels."""
    if card.kind != "two_stage":
        return card.input_scale
    return card.input_scale * card.image_size[0] / image_hw[1]


def preprocess(image: np.ndarray, card: ModelCard, factor: float = 1.0) -> np.ndarray:
    """(H, W, 3) uint8 RGB -> (1, 3, H', W') float32, H' and W' multiples of 16; the image
    resized by ``factor`` x :func:`input_scale_for`."""
    h, w = image.shape[:2]
    scale = input_scale_for((h, w), card) * factor
    sw, sh = max(round(w * scale), 1), max(round(h * scale), 1)
    small = cv2.resize(image, (sw, sh), interpolation=cv2.INTER_AREA)
    ph, pw = -sh % 16, -sw % 16
    if ph or pw:
        small = cv2.copyMakeBorder(small, 0, ph, 0, pw, cv2.BORDER_REPLICATE)
    return normalised(small[None], card.mean, card.std)


def normalised(images: np.ndarray, mean, std) -> np.ndarray:
    """(N, H, W, 3) uint8 RGB -> (N, 3, H, W) float32 ``(pixel / 255 - mean) / std`` per
    channel, the networks' input.

    Written channel by channel into the planar array, in place: the same float32 operations in
    the same order as the whole-array expression, so the same bits, without its three
    temporaries and the transposing copy (0.9 against 5.6 ms for a 640x368 frame on a 2-core
    CPU; ``bench/frontend_speed.py``)."""
    if images.ndim != 4 or images.shape[3] != 3 or images.dtype != np.uint8:
        raise ValueError(
            f"normalised: images must be (N, H, W, 3) uint8, got {images.shape} {images.dtype}"
        )
    mean, std = np.asarray(mean, np.float32), np.asarray(std, np.float32)
    n, h, w = images.shape[:3]
    x = np.empty((n, 3, h, w), np.float32)
    for c in range(3):
        plane = x[:, c]
        np.divide(images[..., c], np.float32(255.0), out=plane, dtype=np.float32)
        plane -= mean[c]
        plane /= std[c]
    return x


def output_to_image(xy_out: np.ndarray, card: ModelCard) -> np.ndarray:
    """Output-grid pixel coordinates (..., 2) -> image pixel coordinates."""
    xy_in = (xy_out + 0.5) * card.output_stride - 0.5
    return (xy_in + 0.5) / card.input_scale - 0.5


class NetworkFrontend:
    """Detections from the ONNX network and voting.

    Args:
        model_path: the .onnx file (its card beside it).
        catalog: the object catalog; the model must have been trained for it.
        threads: onnxruntime intra-op threads.
        deterministic: sequential execution and deterministic kernels where available.
        max_center_std_px: instances whose center standard deviation (sqrt of the trace of its
            covariance, image pixels) exceeds this are dropped.
        spin: onnxruntime's intra-op threads spin for more work after a run (its own default)
            instead of sleeping. Off: the two stages' sessions have a pool each, and a pool
            still spinning after stage one takes the cores from stage two; asleep, the front
            end took 64.8 against 96.1 ms a frame of mixed bins (median) on a 2-core CPU, the
            same detections (``python -m posefuse.bench.frontend_speed [--spin]``).
    """

    def __init__(
        self,
        model_path: str | Path,
        catalog,
        threads: int = 2,
        deterministic: bool = True,
        voting: VotingConfig | None = None,
        seed: int = 0,
        max_center_std_px: float = 15.0,
        spin: bool = False,
    ):
        import onnxruntime as ort

        self.model_path = Path(model_path)
        self.card = load_card(self.model_path)
        classes = tuple((k, m.name) for k, m in sorted(catalog.items()))
        if not self.card.agnostic and (
            self.card.classes != classes or self.card.catalog_hash != catalog_hash(catalog)
        ):
            raise ModelError(
                self.model_path,
                f"trained for classes {list(self.card.classes)} (catalog "
                f"{self.card.catalog_hash}), but the catalog has {list(classes)} "
                f"({catalog_hash(catalog)}); retrain it with posefuse train",
            )
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        if not spin:
            # the pool's threads sleep as soon as a run ends instead of spinning for more work:
            # beside the estimator's threads on few cores, a spinning pool takes their time
            options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        if deterministic:
            options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
            options.add_session_config_entry("session.use_deterministic_compute", "1")
        self.session = _session(ort, self.model_path, options)
        self.crop_session = None
        if self.card.kind == "two_stage":
            fields = {f.name for f in dataclasses.fields(TwoStageConfig)}
            try:
                self.two_stage = TwoStageConfig(
                    **{k: v for k, v in self.card.two_stage.items() if k in fields}
                )
            except (TypeError, ValueError) as exc:
                raise ModelError(self.model_path, f"its card's two_stage settings: {exc}") from None
            crop_path = self.model_path.parent / str(self.card.two_stage.get("crop_model", ""))
            if not crop_path.is_file():
                raise ModelError(crop_path, "the crop model of this two-stage card is missing")
            self.crop_session = _session(ort, crop_path, options)
        self.input_name = self.session.get_inputs()[0].name
        # the obj_id of each stage-one class index: a generalist's one class is "a part"
        self._obj_ids = (
            [AGNOSTIC_CLASSES[0][0]] if self.card.agnostic else [k for k, _ in self.card.classes]
        )
        base = voting or VotingConfig()
        self.voting = dataclasses.replace(base, cov_scale=self.card.cov_scale)
        self.seed = seed
        # a vote this spread out comes from a fragment or a confused field, not a part
        self.max_center_std_px = max_center_std_px
        compile_kernels()  # the voting's loops before the first frame, not during it

    def check_image(self, image: np.ndarray) -> None:
        w, h = self.card.image_size
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
            raise UnsupportedImage("not_uint8", "image: expected a uint8 numpy array")
        if image.ndim != 3 or image.shape[2] != 3:
            raise UnsupportedImage(
                "not_rgb", f"image: expected (H, W, 3) RGB, got shape {image.shape}"
            )
        if self.card.kind == "two_stage":
            if min(image.shape[:2]) < MIN_IMAGE_SIDE:
                raise UnsupportedImage(
                    "too_small",
                    f"image: {image.shape[1]}x{image.shape[0]} is smaller than "
                    f"{MIN_IMAGE_SIDE} px on a side",
                )
        elif image.shape[:2] != (h, w):
            raise UnsupportedImage(
                "wrong_size",
                f"image: the model expects {w}x{h} images, got {image.shape[1]}x{image.shape[0]}",
            )

    def infer(self, image: np.ndarray, factor: float = 1.0) -> np.ndarray:
        """The first network's raw output: (C + 3, h, w) class logits then unit vectors for
        a one-stage model; (C + 4, h, w) heatmaps, box size and offset for a two-stage one
        (its input resized by ``factor`` x the card's scale: see ``class_scale_factors``)."""
        self.check_image(image)
        x = preprocess(image, self.card, factor)
        out = self.session.run(None, {self.input_name: x})[0][0]
        if self.crop_session is not None and self.card.agnostic and out.shape[0] - 4 > 1:
            # a catalog model used as "a part" (``posefuse onboard --steps 0``): a part is
            # wherever any of its class heatmaps peaks; the box size and offset are shared
            out = np.concatenate([out[:-4].max(0, keepdims=True), out[-4:]])
        return out

    def detect(self, image: np.ndarray, frame_seed: int | None = None) -> list[Detection]:
        """Detections in one image (RGB uint8), in a fixed order (class, then votes).

        The centre voting samples pixels with the seed ``[self.seed, frame_seed]``; by default
        ``frame_seed`` is :func:`image_seed` of the image, so that the detections are a
        function of the pixels alone: the same frame gives the same detections in the daemon,
        live or replayed, whatever its stamp, and in ``run-dataset``."""
        self.check_image(image)  # before its pixels are read for the seed
        frame_seed = image_seed(image) if frame_seed is None else frame_seed
        if self.crop_session is not None:
            return self._calibrated(self._detect_two_stage(image, frame_seed))
        return self._calibrated(self._detect_one_stage(image, frame_seed))

    def _calibrated(self, dets: list[Detection]) -> list[Detection]:
        """The card's covariance factor by score applied to each detection's centre."""
        if not self.card.cov_by_score:
            return dets
        return [
            dataclasses.replace(
                d, center_cov=d.center_cov * score_factor(self.card.cov_by_score, d.score)
            )
            for d in dets
        ]

    def _detect_one_stage(self, image: np.ndarray, frame_seed: int) -> list[Detection]:
        out = self.infer(image)
        n_classes = len(self.card.classes)
        logits, vectors = out[: n_classes + 1], out[n_classes + 1 :]
        labels = np.argmax(logits, axis=0)
        h_out, w_out = labels.shape
        flat_logits = logits.reshape(n_classes + 1, -1)
        H, W = image.shape[:2]
        ys, xs = np.mgrid[0:h_out, 0:w_out]
        detections = []
        rng = np.random.default_rng([self.seed, frame_seed])
        scale = 1.0 / (self.card.input_scale / self.card.output_stride)  # image px per out px
        for c, (obj_id, _) in enumerate(self.card.classes, start=1):
            sel = labels == c
            if sel.sum() < self.voting.min_inliers:
                continue
            flat = np.flatnonzero(sel)
            pix = np.stack([xs.reshape(-1)[flat], ys.reshape(-1)[flat]], 1).astype(np.float64)
            vec = vectors.reshape(2, -1)[:, flat].T.astype(np.float64)
            for inst in vote_instances(pix, vec, self.voting, rng):
                cov = inst.cov * scale**2
                if np.sqrt(np.trace(cov)) > self.max_center_std_px:
                    continue
                members = pix[inst.pixels].astype(int)  # (n, 2) output-grid x, y
                x0, y0 = members.min(0)
                x1, y1 = members.max(0) + 1
                crop = np.zeros((y1 - y0, x1 - x0), np.uint8)
                crop[members[:, 1] - y0, members[:, 0] - x0] = 1
                # the instance's output pixels cover [x0, x1) x [y0, y1) of the grid: in the
                # image that is [X0, X1) x [Y0, Y1)
                X0, Y0 = int(round(x0 * scale)), int(round(y0 * scale))
                X1, Y1 = min(int(round(x1 * scale)), W), min(int(round(y1 * scale)), H)
                if X1 <= X0 or Y1 <= Y0:
                    continue
                big = cv2.resize(
                    crop,
                    (int(round((x1 - x0) * scale)), int(round((y1 - y0) * scale))),
                    interpolation=cv2.INTER_NEAREST,
                )
                mask = np.zeros((H, W), bool)
                mask[Y0:Y1, X0:X1] = big[: Y1 - Y0, : X1 - X0] > 0
                bbox = np.array([X0, Y0, X1 - X0, Y1 - Y0], float)
                center = output_to_image(inst.center, self.card)
                lg = flat_logits[:, flat[inst.pixels]]
                e = np.exp(lg - lg.max(0, keepdims=True))
                score = float((e[c] / e.sum(0)).mean())
                detections.append(Detection(obj_id, bbox, center, cov, mask, score))
        return detections

    def crop_infer(self, crops: np.ndarray, masks: np.ndarray | None = None) -> np.ndarray:
        """(N, S, S, 3) uint8 crops [and (N, S, S) uint8 box masks, for a stage two with the
        box channel] -> (N, 3, g, g) stage-two output."""
        x = normalised(crops, self.card.mean, self.card.std)
        if masks is not None:
            x = np.concatenate([x, masks[:, None].astype(np.float32)], 1)
        return self.crop_session.run(None, {self.crop_session.get_inputs()[0].name: x})[0]

    def _detect_two_stage(self, image: np.ndarray, frame_seed: int) -> list[Detection]:
        config = self.two_stage
        boxes = self.boxes(image)
        rng = np.random.default_rng([self.seed, frame_seed])
        votes = self.stage_two_votes(image, boxes, rng)
        for _ in range(config.refine_passes):
            # crop again around each voted center: the part is then the one the crop is
            # centred on, as stage two was trained to expect (a vote whose crop is centred on
            # it already, within ``refine_min_offset`` of the crop's side, is kept as it is)
            kept = [(b, v) for b, v in zip(boxes, votes, strict=True) if v is not None]
            boxes = [Box(b.class_index, v.center, b.size, b.score) for b, v in kept]
            least = [config.refine_min_offset * crop_side(b, config) for b, _ in kept]
            again_at = [
                k
                for k, ((b, v), d) in enumerate(zip(kept, least, strict=True))
                if np.linalg.norm(v.center - b.center) >= d
            ]
            again = self.stage_two_votes(image, [boxes[k] for k in again_at], rng)
            votes = [v for _, v in kept]
            for k, a in zip(again_at, again, strict=True):
                if a is not None:
                    votes[k] = a
        # masks only for the last pass's votes (drawing them was a third of stage two's time)
        obj_ids = self._obj_ids
        dets = [
            detection_of(v, image.shape[:2], obj_ids[b.class_index])
            for b, v in zip(boxes, votes, strict=True)
            if v is not None
        ]
        dets = [
            d
            for d in dets
            if d is not None and np.sqrt(np.trace(d.center_cov)) <= self.max_center_std_px
        ]
        dets = suppress_duplicates(dets, config.duplicate_factor)
        return sorted(dets, key=lambda d: (d.obj_id, -d.score))

    def detect_at(
        self,
        image: np.ndarray,
        expected: list[ExpectedPart],
        frame_seed: int | None = None,
        hint_score: float = 0.3,
        max_offset: float = 0.25,
    ) -> list[Detection]:
        """Stage two on crops where parts are expected (a track's prediction in this view,
        :meth:`MultiViewEstimator.expected_parts`) although stage one gave no box there: the
        detections it finds, each voted within ``max_offset`` of the crop's side from where the
        part was expected (a crop of a neighbour's piece is no detection of the part), scored
        ``hint_score`` times its pixels' mean probability (``hint_score``: the least a stage-one
        box scores), its centre's covariance calibrated as the detector's. Empty for a one-stage
        model. A seed of its own (``frame_seed``, by default :func:`image_seed`; a third entry in
        the seed), so that :meth:`detect` is unchanged."""
        if self.crop_session is None or not expected:
            return []
        config = self.two_stage
        if self.card.agnostic:  # stage two is of any class: the track's class is the crop's
            index = {e.obj_id: 0 for e in expected}
        else:
            index = {k: i for i, (k, _) in enumerate(self.card.classes)}
        wanted = [e for e in expected if e.obj_id in index]
        boxes = [
            Box(index[e.obj_id], np.asarray(e.center_uv, float), np.full(2, e.side_px), hint_score)
            for e in wanted
        ]
        self.check_image(image)
        frame_seed = image_seed(image) if frame_seed is None else frame_seed
        rng = np.random.default_rng([self.seed, frame_seed, 1])
        votes = self.stage_two_votes(image, boxes, rng)
        dets = []
        for e, box, vote in zip(wanted, boxes, votes, strict=True):
            if vote is None:
                continue
            side = max(config.box_scale * e.side_px, config.min_crop_side)
            if np.linalg.norm(vote.center - box.center) > max_offset * side:
                continue
            det = detection_of(vote, image.shape[:2], e.obj_id)
            if det is not None and np.sqrt(np.trace(det.center_cov)) <= self.max_center_std_px:
                dets.append(det)
        return self._calibrated(sorted(dets, key=lambda d: (d.obj_id, -d.score)))

    def boxes(self, image: np.ndarray) -> list[Box]:
        """Stage one of a two-stage model: the boxes and classes in one image, best first."""
        return self.stage_one(image, [self.two_stage])[0]

    def stage_one(self, image: np.ndarray, configs: list[TwoStageConfig]) -> list[list[Box]]:
        """Stage one's boxes decoded under each of ``configs`` (their thresholds, say) from one
        run of the detector per distinct ``class_scale_factors``: each class's boxes from the
        run at its own scale. Each list best first, at most its config's ``max_boxes``."""
        scale = input_scale_for(image.shape[:2], self.card)
        n_classes = len(self.card.classes)
        factors = [self.card.scale_factor_of(c) for c in range(n_classes)]
        levels = sorted(set(factors), reverse=True)
        if len(levels) == 1:
            out = self.infer(image, levels[0])
            return [decode_boxes(out, scale * levels[0], config) for config in configs]
        found: list[list[Box]] = [[] for _ in configs]
        for level in levels:
            out = self.infer(image, level)
            for boxes, config in zip(found, configs, strict=True):
                boxes.extend(
                    b
                    for b in decode_boxes(out, scale * level, config)
                    if factors[b.class_index] == level
                )
        return [
            sorted(boxes, key=lambda b: -b.score)[: config.max_boxes]
            for boxes, config in zip(found, configs, strict=True)
        ]

    def stage_two_votes(self, image: np.ndarray, boxes: list[Box], rng) -> list[CropVote | None]:
        """Stage two of a two-stage model, one pass: each box's center vote (or None), without
        its mask."""
        if not boxes:
            return []
        config = self.two_stage
        crops, transforms = crop_boxes(image, boxes, config)
        masks = box_masks(boxes, transforms, config) if config.box_channel else None
        outs = self.crop_infer(crops, masks)
        return [
            vote_center(out, a, b, box.score, self.voting, config, rng)
            for box, (a, b), out in zip(boxes, transforms, outs, strict=True)
        ]

    def stage_two(self, image: np.ndarray, boxes: list[Box], rng) -> list[Detection | None]:
        """Stage two of a two-stage model, one pass: one detection (or None) per box, before
        the refinement pass, the spread filter and duplicate suppression."""
        obj_ids = self._obj_ids
        return [
            None if v is None else detection_of(v, image.shape[:2], obj_ids[box.class_index])
            for box, v in zip(boxes, self.stage_two_votes(image, boxes, rng), strict=True)
        ]


def _session(ort, path: Path, options):
    try:
        return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own exception types
        raise ModelError(path, f"onnxruntime cannot load it ({exc})") from None
