"""Segment Anything automatic mask generation (docs/methods.md §2), for any SAM kind.

This re-implements the algorithm of the original ``SamAutomaticMaskGenerator`` for the
single-crop case (``crop_n_layers = 0``), running the model directly so that every
threshold is ours. The steps below are SAM's. The model-specific parts (preprocessing,
embedding, prompt decoding to low-res logits and predicted IoUs, the upscaling map) are
small adapters, one per SAM kind (:mod:`vprflow.models.sam.adapters`, which also loads the
models; see there and docs/methods.md §2 for how SAM-HQ and SAM 2 differ); the tensor
operations on masks (upscaling, stability, boxes, NMS, clean-up) are
:mod:`vprflow.models.sam.masks`; the generator that runs the steps is here:

1. Resize the image so its longest side is the model's input size (1024 for the
   published checkpoints), normalise, pad bottom/right to a square; compute the image
   embedding once.
2. Prompt with a regular ``n x n`` grid of single foreground points, ``points_per_batch``
   points at a time, three masks per point (multimask output).
3. Upscale the low-resolution mask logits to the input size, drop the padding, resize to
   the original image size.
4. Keep masks whose predicted IoU is ``> pred_iou_thresh`` and whose stability score
   (IoU of the masks thresholded at ``mask_threshold +- stability_score_offset``) is
   ``>= stability_score_thresh``; a threshold ``<= 0`` disables its filter.
5. Binarise at ``mask_threshold``, box each mask, box NMS (``box_nms_thresh``) with the
   predicted IoU as score.
6. Optionally (``min_mask_region_area > 0``) fill small holes, remove small islands and
   run NMS again, preferring unchanged masks.

Output order is the original's: the NMS order, i.e. descending predicted IoU (ties by
point order, then by the three multimask outputs), which is also the order the published
SegVLAD code stores and reads its masks in. With ``min_mask_region_area > 0`` masks
left unchanged by the clean-up come first, as in the original.

Deviations from the original, all deliberate:

- Masks that are empty after binarisation are dropped (the original only returns them
  when stability filtering is disabled; an empty segment has no centroid downstream).
  They can never suppress or be suppressed in NMS, so nothing else changes.
- Step 3's two bilinear resizes are applied as one composed linear map
  (:class:`vprflow.models.sam.masks.LogitUpscaler`; rounding differs by ~1e-6 in the logits).
- A float input image is quantised to 8 bits before the resize, because the original
  takes ``uint8`` images (8-bit inputs are reproduced exactly).
- Connected components for the small-region clean-up come from ``scipy.ndimage.label``
  (8-connectivity) instead of OpenCV.
- Prompts are decoded by :mod:`vprflow.models.sam.decoder` (the same function with the image-
  side work shared across a batch's prompts; logits agree with transformers' decoder
  to float32 rounding). For SAM-HQ it follows the original ``MaskDecoderHQ``, not
  transformers' ``SamHQMaskDecoder`` (see :mod:`vprflow.models.sam.adapters`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from vprflow.models.sam.masks import box_nms, masks_to_boxes, remove_small_regions, stability_score

# Candidates upscaled at once: their image-sized float32 logits and comparisons are the
# pass's largest intermediates (~5 MB a candidate at 640 x 480).
_UPSCALE_ROWS = 1024


def _free_bytes(device: torch.device) -> int | None:
    """Free memory of an accelerator in bytes, or ``None`` where torch cannot tell."""
    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    return None


def _bytes_per_point(masks_per_point: int, image_size: tuple[int, int]) -> int:
    """Working memory of one prompt point in a pass, generously: the decoder's per-prompt
    intermediates at the published size (~30 MB in float32: 64 x 64 tokens x 256
    channels, several copies) plus its candidates' low-res logits and image-sized
    logits and masks."""
    height, width = image_size
    return 48 * 2**20 + masks_per_point * (256 * 256 * 4 + height * width * 6)


class Adapter(Protocol):
    """What the generator asks of a SAM kind's model (the adapters of
    :mod:`vprflow.models.sam.adapters`): declared here, where it is used, so the
    generator does not import the module that imports it."""

    device: torch.device
    masks_per_point: int

    def preprocess(self, image: np.ndarray) -> tuple[torch.Tensor, tuple[int, int]]: ...
    def embed(self, pixels: torch.Tensor): ...
    def image(self, embedding, index: int): ...
    def decode(self, embedding, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]: ...
    def upscaler(self, *args, **kwargs): ...


# ---------------------------------------------------------------------- prompt points


def point_grid(points_per_side: int) -> np.ndarray:
    """Cell centres of an ``n x n`` grid over the unit square -> float64 ``[n*n, 2]`` (x, y).

    Row-major: y is the slow index, x the fast one (the original's point order).
    """
    offset = 1.0 / (2 * points_per_side)
    side = np.linspace(offset, 1.0 - offset, points_per_side)
    xs = np.tile(side[None, :], (points_per_side, 1))
    ys = np.tile(side[:, None], (1, points_per_side))
    return np.stack([xs.reshape(-1), ys.reshape(-1)], axis=-1)


# ------------------------------------------------------------------------- generator


@dataclass
class SamMaskSet:
    """Everything the generator knows about its output masks (``S`` of them).

    ``candidate`` is each mask's index among all candidates of the image,
    ``point_index * masks_per_point + output_index`` (3 masks per point for SAM and
    SAM 2, 1 for SAM-HQ).
    """

    masks: np.ndarray  # bool [S, H, W]
    iou_preds: np.ndarray  # float32 [S]
    stability_scores: np.ndarray  # float32 [S]
    points: np.ndarray  # float32 [S, 2], (x, y) prompt point in image pixels
    boxes: np.ndarray  # float32 [S, 4], (x0, y0, x1, y1) inclusive
    candidate: np.ndarray  # int64 [S]


class SamSegmenter:
    """Automatic mask generator around a model adapter (see the module docstring)."""

    def __init__(self, adapter: Adapter, params: dict):
        self.adapter = adapter
        self.params = params

    @property
    def device(self) -> torch.device:
        return self.adapter.device

    def masks(self, image: np.ndarray) -> np.ndarray:
        """Image float32 ``[H, W, 3]`` in ``[0, 1]`` -> masks bool ``[S, H, W]``."""
        return self.generate(image).masks

    def masks_batch(self, images: list[np.ndarray]) -> list[np.ndarray]:
        """:meth:`masks` of several images, their embeddings computed in one encoder pass."""
        return [result.masks for result in self.generate_batch(images)]

    @torch.inference_mode()
    def image_embedding(self, image: np.ndarray):
        """Image -> the adapter's embedding (model dtype) and the resized size ``(h, w)``."""
        pixels, input_size = self.adapter.preprocess(image)
        return self.adapter.image(self.adapter.embed(pixels), 0), input_size

    @torch.inference_mode()
    def decode(self, embedding, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Points ``[P, 2]`` in model-input pixels -> low-res logits ``[P, M, h, w]`` and
        predicted IoUs ``[P, M]``, both float32."""
        return self.adapter.decode(embedding, points)

    def prompt_points(self, height: int, width: int, input_size: tuple[int, int]):
        """Grid points in image pixels and in model-input pixels, both float64 ``[P, 2]``."""
        grid = point_grid(int(self.params["points_per_side"]))
        image_points = grid * np.array([width, height], dtype=np.float64)
        model_points = image_points * np.array(
            [input_size[1] / width, input_size[0] / height], dtype=np.float64
        )
        return image_points, model_points

    def generate(self, image: np.ndarray) -> SamMaskSet:
        """Image float32 ``[H, W, 3]`` in ``[0, 1]`` -> :class:`SamMaskSet`."""
        return self.generate_batch([image])[0]

    @torch.inference_mode()
    def generate_batch(self, images: list[np.ndarray]) -> list[SamMaskSet]:
        """Images float32 ``[H, W, 3]`` in ``[0, 1]`` (sizes may differ) -> one
        :class:`SamMaskSet` each. One image-encoder pass for all (the batch that pays on
        a GPU); prompts are decoded image by image."""
        prepared = [self.adapter.preprocess(image) for image in images]
        embedding = self.adapter.embed(torch.cat([pixels for pixels, _ in prepared]))
        return [
            self._generate_one(self.adapter.image(embedding, i), input_size, image.shape[:2])
            for i, (image, (_, input_size)) in enumerate(zip(images, prepared, strict=True))
        ]

    def points_per_pass(self, total: int, image_size: tuple[int, int]) -> int:
        """Prompt points decoded and post-processed together.

        On a CPU ``points_per_batch`` (the decoder then works two prompts at a time, for
        the cache: see the adapters). Elsewhere all the image's points at once, or the
        largest multiple of ``points_per_batch`` whose estimated working memory fits in
        half the device's free memory: one large pass, not many small ones that each
        wait on the host. Results do not depend on it (but for the device's rounding).
        """
        batch = int(self.params["points_per_batch"])
        if self.device.type == "cpu":
            return batch
        free = _free_bytes(self.device)
        if free is None:
            return max(batch, total)
        per_point = _bytes_per_point(self.adapter.masks_per_point, image_size)
        fits = (free // 2) // per_point
        return max(batch, min(total, fits // batch * batch))

    def _generate_one(self, embedding, input_size, image_size) -> SamMaskSet:
        """One image's embedding -> its masks.

        Everything stays on the model's device until the NMS survivors are known; only
        their boxes' suppression matrix (for the sequential NMS) and the final masks
        come to the host.
        """
        p = self.params
        height, width = image_size
        image_points, model_points = self.prompt_points(height, width, input_size)
        per_point = self.adapter.masks_per_point
        upscale = None
        step = self.points_per_pass(len(model_points), image_size)

        kept_masks, kept_iou, kept_stab, kept_index = [], [], [], []
        for start in range(0, len(model_points), step):
            points = torch.from_numpy(model_points[start : start + step])
            low_res, iou_preds = self.decode(embedding, points)
            if upscale is None:
                upscale = self.adapter.upscaler(
                    tuple(low_res.shape[-2:]), input_size, (height, width)
                )
            iou_preds = iou_preds.flatten()  # [M*P], candidate-major as the original
            first = start * per_point
            index = torch.arange(first, first + iou_preds.shape[0], device=self.device)
            # The IoU filter needs no logits: apply it before the (costly) upscaling,
            # as the original does.
            low_res = low_res.flatten(0, 1)
            if p["pred_iou_thresh"] > 0.0:
                keep = iou_preds > p["pred_iou_thresh"]
                iou_preds, index, low_res = iou_preds[keep], index[keep], low_res[keep]
            for part in range(0, max(len(low_res), 1), _UPSCALE_ROWS):  # once if none
                rows = slice(part, part + _UPSCALE_ROWS)
                masks, stability, keep = self._binary_masks(upscale, low_res[rows])
                kept_masks.append(masks)
                kept_iou.append(iou_preds[rows][keep])
                kept_stab.append(stability)
                kept_index.append(index[rows][keep])
            del low_res

        masks = torch.cat(kept_masks)
        boxes = masks_to_boxes(masks)
        keep = box_nms(boxes, torch.cat(kept_iou), float(p["box_nms_thresh"]))
        masks = masks[keep].cpu()
        iou_preds = torch.cat(kept_iou)[keep].cpu()
        stability = torch.cat(kept_stab)[keep].cpu()
        candidate = torch.cat(kept_index)[keep].cpu()
        boxes = boxes[keep].cpu()

        if p["min_mask_region_area"] > 0 and len(masks):
            masks_np, boxes_np, order = self._clean_small_regions(masks.numpy())
            masks = torch.from_numpy(masks_np)
            iou_preds, stability = iou_preds[order], stability[order]
            candidate, boxes = candidate[order], torch.from_numpy(boxes_np)

        return SamMaskSet(
            masks=masks.numpy().astype(bool, copy=False),
            iou_preds=iou_preds.numpy().astype(np.float32),
            stability_scores=stability.numpy().astype(np.float32),
            points=image_points[candidate.numpy() // per_point].astype(np.float32),
            boxes=boxes.numpy().astype(np.float32),
            candidate=candidate.numpy().astype(np.int64),
        )

    def _binary_masks(self, upscale, low_res: torch.Tensor):
        """Low-res logits ``[N, h, w]`` -> the binary masks ``[K, H, W]`` that pass the
        stability filter and are not empty, their stability ``[K]`` and which of the
        ``N`` they are (bool ``[N]``)."""
        p = self.params
        mask_threshold = float(p["mask_threshold"])
        logits = upscale(low_res)  # [N, H, W]
        stability = stability_score(logits, mask_threshold, float(p["stability_score_offset"]))
        binary = logits > mask_threshold
        del logits
        keep = binary.flatten(1).any(1)
        if p["stability_score_thresh"] > 0.0:
            keep &= stability >= p["stability_score_thresh"]
        return binary[keep], stability[keep], keep

    def _clean_small_regions(self, masks: np.ndarray):
        """Masks bool ``[S, H, W]`` -> cleaned masks ``[S', H, W]``, their boxes, and the
        indices ``[S']`` of the input masks they came from (the original's second NMS,
        scoring unchanged masks 1 and changed ones 0)."""
        area = float(self.params["min_mask_region_area"])
        cleaned, scores = [], []
        for mask in masks:
            mask, changed_holes = remove_small_regions(mask, area, "holes")
            mask, changed_islands = remove_small_regions(mask, area, "islands")
            cleaned.append(mask)
            scores.append(0.0 if (changed_holes or changed_islands) else 1.0)
        cleaned_t = torch.from_numpy(np.stack(cleaned))
        boxes = masks_to_boxes(cleaned_t)
        keep = box_nms(boxes, torch.tensor(scores), float(self.params["box_nms_thresh"]))
        return cleaned_t[keep].numpy(), boxes[keep].numpy(), keep
