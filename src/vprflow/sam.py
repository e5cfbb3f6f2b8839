"""Segment Anything automatic mask generation on top of transformers' ``SamModel``,
``SamHQModel`` and ``Sam2Model``.

This re-implements the algorithm of the original ``SamAutomaticMaskGenerator`` for the
single-crop case (``crop_n_layers = 0``), running the model directly so that every
threshold is ours. The steps below are SAM's; the model-specific parts (preprocessing,
embedding, prompt decoding to low-res logits and predicted IoUs, the upscaling map) are
small adapters (:class:`SamAdapter`, :class:`SamHQAdapter`, :class:`Sam2Adapter`; see
their docstrings and docs/methods.md §2 for how SAM-HQ and SAM 2 differ), the rest is
shared:

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
- Step 3's two bilinear resizes are applied as one composed separable linear map, which
  is mathematically identical to the original's ``interpolate -> crop -> interpolate``
  but never materialises the ``[B, 1024, 1024]`` intermediate (rounding differs by
  ~1e-6 in the logits).
- A float input image is quantised to 8 bits before the resize, because the original
  takes ``uint8`` images (8-bit inputs are reproduced exactly).
- Connected components for the small-region clean-up come from ``scipy.ndimage.label``
  (8-connectivity) instead of OpenCV.
- Prompts are decoded by :mod:`vprflow.sam_decoder` (the same function with the image-
  side work shared across a batch's prompts; logits agree with transformers' decoder
  to float32 rounding). For SAM-HQ it follows the original ``MaskDecoderHQ``, which
  upscales the two-way transformer's output: transformers' ``SamHQMaskDecoder``
  upscales the embedding from before the transformer (``shared_decoder=False`` keeps
  transformers' behaviour, for comparison only).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from PIL import Image

from vprflow import sam_decoder
from vprflow.registry import SEGMENTERS, with_defaults

# The original automatic mask generator's defaults (ViT-H), stated in the registry.
SAM_DEFAULTS: dict = SEGMENTERS["sam"].defaults

# The original SAM's normalisation constants, in 0..255 units (= ImageNet mean/std).
PIXEL_MEAN = np.array([123.675, 116.28, 103.53], dtype=np.float32)
PIXEL_STD = np.array([58.395, 57.12, 57.375], dtype=np.float32)


# --------------------------------------------------------------------------- geometry


def point_grid(points_per_side: int) -> np.ndarray:
    """Cell centres of an ``n x n`` grid over the unit square -> float64 ``[n*n, 2]`` (x, y).

    Row-major: y is the slow index, x the fast one (the original's point order).
    """
    offset = 1.0 / (2 * points_per_side)
    side = np.linspace(offset, 1.0 - offset, points_per_side)
    xs = np.tile(side[None, :], (points_per_side, 1))
    ys = np.tile(side[:, None], (1, points_per_side))
    return np.stack([xs.reshape(-1), ys.reshape(-1)], axis=-1)


def preprocess_shape(height: int, width: int, long_side: int) -> tuple[int, int]:
    """Size ``(new_h, new_w)`` of an image resized so its longest side is ``long_side``."""
    scale = long_side * 1.0 / max(height, width)
    return int(height * scale + 0.5), int(width * scale + 0.5)


def preprocess_image(image: np.ndarray, long_side: int) -> tuple[torch.Tensor, tuple[int, int]]:
    """Image float32 ``[H, W, 3]`` in ``[0, 1]`` -> model input ``[1, 3, L, L]`` and ``(h, w)``.

    ``(h, w)`` is the size of the resized image inside the zero-padded ``L x L`` square
    (zero after normalisation = the mean colour, as in the original).
    """
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an RGB image [H, W, 3], got shape {image.shape}")
    height, width = image.shape[:2]
    new_h, new_w = preprocess_shape(height, width, long_side)
    pixels = np.clip(np.rint(np.asarray(image, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)
    # PIL bilinear on uint8 RGB is exactly what the original's ResizeLongestSide does.
    resized = Image.fromarray(np.ascontiguousarray(pixels)).resize(
        (new_w, new_h), Image.Resampling.BILINEAR
    )
    normalised = (np.asarray(resized, dtype=np.float32) - PIXEL_MEAN) / PIXEL_STD
    padded = np.zeros((long_side, long_side, 3), dtype=np.float32)
    padded[:new_h, :new_w] = normalised
    return torch.from_numpy(padded).permute(2, 0, 1)[None].contiguous(), (new_h, new_w)


def bilinear_matrix(in_size: int, out_size: int) -> np.ndarray:
    """Dense float64 ``[out_size, in_size]`` matrix of 1-D bilinear resizing.

    Reproduces ``torch.nn.functional.interpolate(mode="bilinear", align_corners=False,
    antialias=False)`` with an explicit output size along one axis.
    """
    matrix = np.zeros((out_size, in_size), dtype=np.float64)
    scale = in_size / out_size
    for dst in range(out_size):
        src = max((dst + 0.5) * scale - 0.5, 0.0)
        low = min(int(src), in_size - 1)
        high = min(low + 1, in_size - 1)
        frac = min(max(src - low, 0.0), 1.0)
        matrix[dst, low] += 1.0 - frac
        matrix[dst, high] += frac
    return matrix


def upscale_matrix(low_res: int, model_size: int, valid: int, out_size: int) -> np.ndarray:
    """Composed 1-D map ``[out_size, low_res]``: resize to ``model_size``, keep the first
    ``valid`` samples (drop padding), resize to ``out_size``."""
    first = bilinear_matrix(low_res, model_size)[:valid]
    return bilinear_matrix(valid, out_size) @ first


class LogitUpscaler:
    """Low-res logits ``[N, h, w]`` -> logits at the original image size ``[N, H, W]``.

    The composed resize is applied as two dense matmuls: each output sample depends on
    at most four inputs, but BLAS beats a gather here by an order of magnitude.
    """

    def __init__(
        self,
        low_res: tuple[int, int],
        model_size: int,
        input_size: tuple[int, int],
        original_size: tuple[int, int],
        device: torch.device,
    ):
        rows = upscale_matrix(low_res[0], model_size, input_size[0], original_size[0])
        cols = upscale_matrix(low_res[1], model_size, input_size[1], original_size[1])
        self.rows = torch.from_numpy(rows.astype(np.float32)).to(device)  # [H, h]
        self.cols_t = torch.from_numpy(cols.T.astype(np.float32)).to(device)  # [w, W]
        height, width = original_size
        # Resize the axis first whose multiply is cheaper (the output sizes differ).
        self.rows_first = height * low_res[1] * (low_res[0] + width) <= width * low_res[0] * (
            low_res[1] + height
        )

    def __call__(self, logits: torch.Tensor) -> torch.Tensor:
        logits = logits.float()
        if self.rows_first:
            return torch.matmul(torch.matmul(self.rows, logits), self.cols_t)
        return torch.matmul(self.rows, torch.matmul(logits, self.cols_t))


# --------------------------------------------------------------------- mask statistics


def stability_score(logits: torch.Tensor, mask_threshold: float, offset: float) -> torch.Tensor:
    """Stability of mask logits ``[N, H, W]`` -> float32 ``[N]``.

    ``|logits > t + offset| / |logits > t - offset|``; 0/0 gives NaN (as the original),
    which fails every threshold.
    """
    high = (logits > (mask_threshold + offset)).flatten(1).sum(1, dtype=torch.int64)
    low = (logits > (mask_threshold - offset)).flatten(1).sum(1, dtype=torch.int64)
    return high.to(torch.float32) / low.to(torch.float32)


def masks_to_boxes(masks: torch.Tensor) -> torch.Tensor:
    """Boolean masks ``[N, H, W]`` -> float32 boxes ``[N, 4]`` (x0, y0, x1, y1).

    As the original: ``x1``/``y1`` are the last covered column/row (inclusive, so a
    one-pixel mask has a zero-area box); an empty mask gets ``[0, 0, 0, 0]``.
    """
    n, height, width = masks.shape
    if n == 0:
        return torch.zeros((0, 4), dtype=torch.float32, device=masks.device)
    rows = masks.any(dim=2)  # [N, H]
    cols = masks.any(dim=1)  # [N, W]
    row_index = torch.arange(height, device=masks.device)
    col_index = torch.arange(width, device=masks.device)
    bottom = torch.where(rows, row_index, -1).amax(1)
    top = torch.where(rows, row_index, height).amin(1)
    right = torch.where(cols, col_index, -1).amax(1)
    left = torch.where(cols, col_index, width).amin(1)
    boxes = torch.stack([left, top, right, bottom], dim=1)
    empty = ~rows.any(dim=1)
    return torch.where(empty[:, None], 0, boxes).to(torch.float32)


def box_nms(boxes: torch.Tensor, scores: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    """Greedy non-maximum suppression -> kept indices, long ``[K]``, by descending score.

    ``boxes`` ``[N, 4]`` are ``(x0, y0, x1, y1)``; ``scores`` ``[N]``. Equal scores keep
    their input order (stable sort), so the result is deterministic. A box is removed
    when its IoU with a kept higher-scored box is ``> iou_threshold``; areas are
    ``(x1 - x0) * (y1 - y0)`` and an IoU of 0/0 (two zero-area boxes) suppresses nothing,
    as in torchvision's ``nms``. Computed in float64 on the CPU (a sequential loop).
    """
    device = boxes.device
    n = boxes.shape[0]
    if n == 0:
        return torch.zeros(0, dtype=torch.long, device=device)
    order = torch.sort(scores.detach().cpu(), descending=True, stable=True).indices
    x0, y0, x1, y1 = boxes.detach().cpu().to(torch.float64)[order].unbind(1)
    areas = (x1 - x0) * (y1 - y0)
    suppressed = torch.zeros(n, dtype=torch.bool)
    keep = []
    for i in range(n):
        if suppressed[i]:
            continue
        keep.append(i)
        rest = slice(i + 1, n)
        width = (torch.minimum(x1[i], x1[rest]) - torch.maximum(x0[i], x0[rest])).clamp(min=0)
        height = (torch.minimum(y1[i], y1[rest]) - torch.maximum(y0[i], y0[rest])).clamp(min=0)
        inter = width * height
        iou = inter / (areas[i] + areas[rest] - inter)
        suppressed[rest] |= iou > iou_threshold  # NaN compares False: never suppresses
    return order[torch.tensor(keep, dtype=torch.long)].to(device)


def remove_small_regions(
    mask: np.ndarray, area_thresh: float, mode: str
) -> tuple[np.ndarray, bool]:
    """Fill holes (``mode="holes"``) or drop islands (``"islands"``) smaller than
    ``area_thresh`` pixels in a boolean mask ``[H, W]`` -> ``(mask, changed)``.

    8-connected components. When every island is small, the largest one is kept.
    """
    from scipy import ndimage

    if mode not in ("holes", "islands"):
        raise ValueError(f"mode must be 'holes' or 'islands', got {mode!r}")
    holes = mode == "holes"
    working = holes ^ mask.astype(bool)
    labels, n_labels = ndimage.label(working, structure=np.ones((3, 3), dtype=bool))
    sizes = np.bincount(labels.ravel(), minlength=n_labels + 1)[1:]
    small = [i + 1 for i, size in enumerate(sizes) if size < area_thresh]
    if not small:
        return mask.astype(bool), False
    fill = [0, *small]
    if not holes:
        fill = [i for i in range(n_labels + 1) if i not in fill]
        if not fill:
            fill = [int(np.argmax(sizes)) + 1]
    return np.isin(labels, fill), True


# --------------------------------------------------------------------------- adapters

# Prompts decoded per pass on a CPU: one pass's image-sized intermediates (~17 MB per
# prompt in float32) then stay in the last-level cache. Measured on a 2-core EPYC with
# 32 MB L3 (benchmarks/bench_sam.py --decoders): 64 prompts at once 3.7 s, 16: 1.8 s,
# 4: 1.5 s, 2: 1.15 s, 1: 1.3 s (float32). A GPU takes the whole batch in one pass.
CPU_PROMPTS_PER_PASS = 2
#
# An adapter is the model-specific part of automatic mask generation: preprocessing,
# the image embedding, and prompt decoding to low-resolution logits and predicted IoUs.
# Everything else (point grid, upscaling, filters, NMS, clean-up) is shared.


class SamAdapter:
    """transformers ``SamModel``: longest side resized to the model size with PIL
    bilinear, SAM's mean/std, zero padding; three masks per point; logits upscaled to
    the padded input, cropped, then resized (the original ``postprocess_masks``).

    Prompts are decoded by :mod:`vprflow.sam_decoder` (the image-side work shared by a
    batch's prompts); ``shared_decoder=False`` calls the transformers model instead (for
    SAM and SAM 2 the same function, float32 rounding apart; for SAM-HQ transformers'
    decoder differs from the original: see the module docstring). For benchmarks.
    """

    masks_per_point = 3

    def __init__(
        self, model, device: torch.device, dtype: torch.dtype, shared_decoder: bool = True
    ):
        self.model = model
        self.device = torch.device(device)
        self.dtype = dtype
        self.shared_decoder = bool(shared_decoder)
        self._image_pe = None
        self.prompts_per_pass = CPU_PROMPTS_PER_PASS if self.device.type == "cpu" else None
        self.model_size = self._model_size(model.config)

    @staticmethod
    def _model_size(config) -> int:
        """The square input side of the model, checked against the prompt encoder's."""
        size = int(config.vision_config.image_size)
        prompt_size = int(config.prompt_encoder_config.image_size)
        if prompt_size != size:
            raise ValueError(
                f"SAM config mismatch: vision image_size {size} != prompt encoder "
                f"image_size {prompt_size}"
            )
        return size

    def preprocess(self, image: np.ndarray) -> tuple[torch.Tensor, tuple[int, int]]:
        """Image ``[H, W, 3]`` in ``[0, 1]`` -> model input ``[1, 3, L, L]`` (float32, on
        the CPU) and the size ``(h, w)`` of the image inside it."""
        return preprocess_image(image, self.model_size)

    def embed(self, pixels: torch.Tensor):
        """Model input ``[B, 3, L, L]`` -> the images' embedding, in whatever form
        :meth:`image` takes."""
        return self.model.get_image_embeddings(pixels.to(device=self.device, dtype=self.dtype))

    def image(self, embedding, index: int):
        """Image ``index`` of a batch's embedding, in the form :meth:`decode` takes."""
        if isinstance(embedding, torch.Tensor):
            return embedding[index : index + 1]
        parts = [self.image(part, index) for part in embedding]  # SAM-HQ, SAM 2: several
        return parts if isinstance(embedding, list) else tuple(parts)

    def _prompts(self, points: torch.Tensor) -> dict:
        count = points.shape[0]
        return {
            "input_points": points.to(self.device, torch.float32).reshape(1, count, 1, 2),
            "input_labels": torch.ones((1, count, 1), dtype=torch.int64, device=self.device),
        }

    def _prompt_embeddings(self, points: torch.Tensor):
        """Points ``[P, 2]`` -> the prompt encoder's sparse ``[1, P, S, C]`` and dense
        ``[1, C, h, w]`` embeddings, and the image-wide positional encoding."""
        if self._image_pe is None:
            self._image_pe = self.model.get_image_wide_positional_embeddings()
        sparse, dense = self.model.prompt_encoder(
            **self._prompts(points), input_boxes=None, input_masks=None
        )
        return sparse, dense, self._image_pe

    def decode(self, embedding, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Points ``[P, 2]`` in model-input pixels -> low-res logits ``[P, M, h, w]`` and
        predicted IoUs ``[P, M]`` (``M = masks_per_point``), float32, on the device."""
        if self.shared_decoder:
            sparse, dense, image_pe = self._prompt_embeddings(points)
            logits, iou = self._shared_decode(embedding, image_pe, sparse, dense)
        else:
            logits, iou = self._transformers_decode(embedding, points)
        return logits.float(), iou.float()

    def _shared_decode(self, embedding, image_pe, sparse, dense):
        return sam_decoder.decode_sam(
            self.model.mask_decoder, embedding, image_pe, sparse, dense, self.prompts_per_pass
        )

    def _transformers_decode(self, embedding, points):
        output = self.model(
            image_embeddings=embedding, **self._prompts(points), multimask_output=True
        )
        return output.pred_masks[0], output.iou_scores[0]

    def upscaler(
        self, low_res: tuple[int, int], input_size: tuple[int, int], original_size: tuple[int, int]
    ) -> LogitUpscaler:
        return LogitUpscaler(low_res, self.model_size, input_size, original_size, self.device)


class SamHQAdapter(SamAdapter):
    """transformers ``SamHQModel``: SAM's preprocessing and upscaling; the embedding is the
    final one plus the ViT's early global-attention features the HQ decoder fuses.

    One mask per point, as SAM-HQ's ``SamAutomaticMaskGenerator`` (multimask output on,
    ``hq_token_only`` off by default): its HQ decoder returns the best of SAM's three
    multimask logits (highest predicted IoU) plus the HQ token's logits, with that best
    IoU. transformers returns all three SAM logits sorted by predicted IoU, each plus the
    HQ logits; the first of them is that mask. With ``hq_token_only`` the HQ logits alone.
    """

    masks_per_point = 1

    def __init__(self, model, device, dtype, hq_token_only: bool = False, shared_decoder=True):
        super().__init__(model, device, dtype, shared_decoder)
        self.hq_token_only = bool(hq_token_only)

    def embed(self, pixels):
        embedding, intermediate = self.model.get_image_embeddings(
            pixels.to(device=self.device, dtype=self.dtype)
        )
        return embedding, intermediate

    def _shared_decode(self, embedding, image_pe, sparse, dense):
        final, intermediate = embedding
        return sam_decoder.decode_sam_hq(
            self.model.mask_decoder,
            final,
            intermediate,
            image_pe,
            sparse,
            dense,
            self.hq_token_only,
            self.prompts_per_pass,
        )

    def _transformers_decode(self, embedding, points):
        final, intermediate = embedding
        output = self.model(
            image_embeddings=final,
            intermediate_embeddings=intermediate,
            hq_token_only=self.hq_token_only,
            multimask_output=True,
            **self._prompts(points),
        )
        return output.pred_masks[0, :, :1], output.iou_scores[0, :, :1]


# SAM 2's normalisation (SAM2Transforms; = transformers' Sam2ImageProcessor), 0..1 units.
SAM2_MEAN = (0.485, 0.456, 0.406)
SAM2_STD = (0.229, 0.224, 0.225)


def preprocess_image_sam2(image: np.ndarray, size: int) -> tuple[torch.Tensor, tuple[int, int]]:
    """Image float32 ``[H, W, 3]`` in ``[0, 1]`` -> SAM 2 input ``[1, 3, L, L]`` and ``(L, L)``.

    As SAM 2's ``SAM2Transforms``: the 8-bit image as floats in ``[0, 1]``, resized to
    ``L x L`` (aspect ratio not kept, no padding) bilinearly with antialiasing
    (torchvision ``Resize`` on a tensor), then normalised with ImageNet mean/std.
    """
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an RGB image [H, W, 3], got shape {image.shape}")
    pixels = np.clip(np.rint(np.asarray(image, dtype=np.float64) * 255.0), 0, 255)
    tensor = torch.from_numpy((pixels / 255.0).astype(np.float32)).permute(2, 0, 1)[None]
    resized = torch.nn.functional.interpolate(
        tensor, (size, size), mode="bilinear", align_corners=False, antialias=True
    )
    mean = torch.tensor(SAM2_MEAN, dtype=torch.float32).view(1, 3, 1, 1)
    std = torch.tensor(SAM2_STD, dtype=torch.float32).view(1, 3, 1, 1)
    return ((resized - mean) / std).contiguous(), (size, size)


class Sam2Adapter(SamAdapter):
    """transformers ``Sam2Model``: the image stretched to ``L x L`` (``L`` = 1024 for the
    published checkpoints); the embedding is the FPN's three levels (the two high-
    resolution ones feed the decoder's upsampling); three masks per point; low-res logits
    resized straight to the image size (SAM 2's ``postprocess_masks``: no padding)."""

    @staticmethod
    def _model_size(config) -> int:
        size = int(config.prompt_encoder_config.image_size)
        vision = config.vision_config.backbone_config.image_size
        vision = [vision, vision] if isinstance(vision, int) else list(vision)
        if vision != [size, size]:
            raise ValueError(
                f"Sam2Model config mismatch: backbone image_size {vision} != prompt encoder "
                f"image_size {size}"
            )
        return size

    def _shared_decode(self, embedding, image_pe, sparse, dense):
        return sam_decoder.decode_sam2(
            self.model.mask_decoder, embedding, image_pe, sparse, dense, self.prompts_per_pass
        )

    def preprocess(self, image):
        return preprocess_image_sam2(image, self.model_size)

    def upscaler(self, low_res, input_size, original_size):
        if low_res[0] != low_res[1]:
            raise ValueError(f"expected square low-res logits, got {low_res}")
        # Resizing to low_res first is the identity: one bilinear resize to the image.
        return LogitUpscaler(low_res, low_res[0], low_res, original_size, self.device)


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

    def __init__(self, adapter: SamAdapter, params: dict):
        self.adapter = adapter
        self.params = params

    @property
    def model(self):
        return self.adapter.model

    @property
    def device(self) -> torch.device:
        return self.adapter.device

    @property
    def dtype(self) -> torch.dtype:
        return self.adapter.dtype

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

    def _generate_one(self, embedding, input_size, image_size) -> SamMaskSet:
        """One image's embedding -> its masks.

        Everything stays on the model's device until the NMS survivors are known; only
        their boxes (for the sequential NMS) and the final masks come to the host.
        """
        p = self.params
        height, width = image_size
        image_points, model_points = self.prompt_points(height, width, input_size)
        per_point = self.adapter.masks_per_point
        upscale = None
        mask_threshold = float(p["mask_threshold"])
        batch = int(p["points_per_batch"])

        kept_masks, kept_iou, kept_stab, kept_index = [], [], [], []
        for start in range(0, len(model_points), batch):
            points = torch.from_numpy(model_points[start : start + batch])
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
            logits = upscale(low_res)  # [N, H, W]
            stability = stability_score(logits, mask_threshold, float(p["stability_score_offset"]))
            if p["stability_score_thresh"] > 0.0:
                keep = stability >= p["stability_score_thresh"]
                logits, iou_preds, index, stability = (
                    logits[keep],
                    iou_preds[keep],
                    index[keep],
                    stability[keep],
                )
            binary = logits > mask_threshold
            nonempty = binary.flatten(1).any(1)
            kept_masks.append(binary[nonempty])
            kept_iou.append(iou_preds[nonempty])
            kept_stab.append(stability[nonempty])
            kept_index.append(index[nonempty])
            del logits, binary

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


# ---------------------------------------------------------------------------- loading

# kind: (transformers class name, adapter class)
SAM_KINDS = {
    "sam": ("SamModel", SamAdapter),
    "sam_hq": ("SamHQModel", SamHQAdapter),
    "sam2": ("Sam2Model", Sam2Adapter),
}


def sam_params(params: dict, kind: str = "sam") -> dict:
    """Config dict -> complete parameters of SAM kind ``kind`` (its registry defaults
    filled, values validated). Keys outside those defaults (e.g. ``segmenter``) are
    ignored."""
    if kind not in SAM_KINDS:
        raise ValueError(f"unknown SAM kind {kind!r}; expected one of {sorted(SAM_KINDS)}")
    defaults = SEGMENTERS[kind].defaults
    filled = with_defaults("segments", {**params, "segmenter": kind})
    merged = {key: filled[key] for key in defaults}
    if int(merged["points_per_side"]) < 1 or int(merged["points_per_batch"]) < 1:
        raise ValueError("points_per_side and points_per_batch must be >= 1")
    if float(merged["stability_score_offset"]) < 0:
        raise ValueError("stability_score_offset must be >= 0")
    return merged


def load_segmenter(kind: str, params: dict, device: str = "auto") -> SamSegmenter:
    """Load a model of SAM kind ``kind`` (hub id or local directory, scaled-dot-product
    attention) as a :class:`SamSegmenter`.

    Raises ``vprflow.models.ModelNotFoundError`` naming the model when it is neither a
    local directory nor obtainable from the hub.
    """
    import transformers

    from vprflow.devices import resolve_device, resolve_dtype
    from vprflow.models import load_pretrained, resolve_model_source

    merged = sam_params(params, kind)
    class_name, adapter_class = SAM_KINDS[kind]
    torch_device = resolve_device(device)
    dtype = resolve_dtype(merged["dtype"], torch_device)
    source = resolve_model_source(str(merged["model"]), merged["cache_dir"])
    load = getattr(transformers, class_name).from_pretrained
    model = load_pretrained(load, source, str(merged["model"]), attn_implementation="sdpa")
    model = model.to(device=torch_device, dtype=dtype).eval()
    extra = {"hq_token_only": merged["hq_token_only"]} if kind == "sam_hq" else {}
    return SamSegmenter(adapter_class(model, torch_device, dtype, **extra), merged)


def load_sam(params: dict, device: str = "auto") -> SamSegmenter:
    """Segment Anything (``segmenter: sam``); defaults :data:`SAM_DEFAULTS` (the original
    library's, ViT-H)."""
    return load_segmenter("sam", params, device)


def load_sam_hq(params: dict, device: str = "auto") -> SamSegmenter:
    """SAM-HQ (``segmenter: sam_hq``); defaults: the registry's (SAM-HQ's automatic
    generator = SAM's, HQ output, ViT-H)."""
    return load_segmenter("sam_hq", params, device)


def load_sam2(params: dict, device: str = "auto") -> SamSegmenter:
    """SAM 2 (``segmenter: sam2``); defaults: the registry's (SAM 2's automatic
    generator, Hiera-L)."""
    return load_segmenter("sam2", params, device)
