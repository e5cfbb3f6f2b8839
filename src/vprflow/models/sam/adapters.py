"""The SAM kinds (``segmenter: sam``, ``sam_hq``, ``sam2``; docs/methods.md §2) over
transformers' ``SamModel``, ``SamHQModel`` and ``Sam2Model``: how each is loaded and run.

An adapter is the model-specific part of automatic mask generation: preprocessing,
the image embedding, prompt decoding to low-resolution logits and predicted IoUs, and
the upscaling map (:class:`SamAdapter`, :class:`SamHQAdapter`, :class:`Sam2Adapter`;
see their docstrings). Everything else (point grid, filters, NMS, clean-up) is the
shared generator, :class:`vprflow.models.sam.generator.SamSegmenter`; the loader of
every SAM kind, :func:`load_sam`, returns one around the kind's adapter (its
:class:`vprflow.models.kinds.SamKind` names the transformers class, which picks the
adapter: :data:`ADAPTERS`).

Prompts are decoded by :mod:`vprflow.models.sam.decoder` (the same function with the image-side
work shared across a batch's prompts). For SAM-HQ it follows the original
``MaskDecoderHQ``, which upscales the two-way transformer's output: transformers'
``SamHQMaskDecoder`` upscales the embedding from before the transformer
(``shared_decoder=False`` keeps transformers' behaviour, for comparison only).
"""

from __future__ import annotations

import numpy as np
import torch
import transformers
from PIL import Image

from vprflow.core.devices import resolve_device, resolve_dtype
from vprflow.models.hub import load_pretrained, resolve_model_source
from vprflow.models.kinds import IMAGENET_MEAN, IMAGENET_STD, SEGMENTERS, SamKind, with_defaults
from vprflow.models.sam import decoder as sam_decoder
from vprflow.models.sam.generator import SamSegmenter
from vprflow.models.sam.masks import LogitUpscaler

# ---------------------------------------------------------------------- preprocessing

# The original SAM's normalisation constants, in 0..255 units (= ImageNet mean/std).
PIXEL_MEAN = np.array([123.675, 116.28, 103.53], dtype=np.float32)
PIXEL_STD = np.array([58.395, 57.12, 57.375], dtype=np.float32)


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


# SAM 2's normalisation (SAM2Transforms; = transformers' Sam2ImageProcessor), 0..1 units.
SAM2_MEAN, SAM2_STD = IMAGENET_MEAN, IMAGENET_STD


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


# --------------------------------------------------------------------------- adapters

# Prompts decoded per pass on a CPU: one pass's image-sized intermediates (~17 MB per
# prompt in float32) then stay in the last-level cache. Measured on a 2-core EPYC with
# 32 MB L3 (benchmarks/bench_sam.py --decoders): 64 prompts at once 3.7 s, 16: 1.8 s,
# 4: 1.5 s, 2: 1.15 s, 1: 1.3 s (float32). A GPU takes the whole batch in one pass.
CPU_PROMPTS_PER_PASS = 2


class SamAdapter:
    """transformers ``SamModel``: longest side resized to the model size with PIL
    bilinear, SAM's mean/std, zero padding; three masks per point; logits upscaled to
    the padded input, cropped, then resized (the original ``postprocess_masks``).

    Prompts are decoded by :mod:`vprflow.models.sam.decoder` (the image-side work shared by a
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


# ---------------------------------------------------------------------------- loading


def sam_params(params: dict, kind: str = "sam") -> dict:
    """Config dict -> complete parameters of SAM kind ``kind`` (its defaults of
    models/kinds.py filled, values validated). Keys outside those defaults (e.g. ``segmenter``) are
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
    attention) as a :class:`SamSegmenter`: the kind's transformers class around its
    adapter, which gets the entry's ``adapter_options``.

    Raises ``vprflow.models.hub.ModelNotFoundError`` naming the model when it is neither a
    local directory nor obtainable from the hub.
    """
    merged = sam_params(params, kind)
    spec = SEGMENTERS[kind].spec
    class_name, adapter_class = SAM_KINDS[kind]
    torch_device = resolve_device(device)
    dtype = resolve_dtype(merged["dtype"], torch_device)
    source = resolve_model_source(str(merged["model"]), merged["cache_dir"])
    load = getattr(transformers, class_name).from_pretrained
    model = load_pretrained(load, source, str(merged["model"]), attn_implementation="sdpa")
    model = model.to(device=torch_device, dtype=dtype).eval()
    extra = {name: merged[name] for name in spec.adapter_options}
    return SamSegmenter(adapter_class(model, torch_device, dtype, **extra), merged)


def load_sam(params: dict, device: str = "auto") -> SamSegmenter:
    """The loader of every SAM kind: the kind its ``segmenter`` names (``sam`` when it
    names none), defaults its entry's in models/kinds.py (each kind's own generator's)."""
    return load_segmenter(params.get("segmenter") or "sam", params, device)


# transformers class name -> the adapter that runs a model of it.
ADAPTERS = {"SamModel": SamAdapter, "SamHQModel": SamHQAdapter, "Sam2Model": Sam2Adapter}

# kind -> (transformers class name, adapter class), from the SAM entries of
# models/kinds.py, each kind named there once.
SAM_KINDS = {
    name: (kind.spec.model_class, ADAPTERS[kind.spec.model_class])
    for name, kind in SEGMENTERS.items()
    if isinstance(kind.spec, SamKind)
}
