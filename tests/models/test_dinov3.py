"""DINOv3 feature extraction, checked against hand computations on tiny models.

The models are randomly initialised ``DINOv3ViTModel``s (RoPE, 1 CLS + register tokens,
layer scale, no key bias) saved to a temporary directory and loaded through the real
loader. Every parameter, LayerNorms, layer scales and biases included, is re-drawn with
a large spread so that a wrong norm, a swapped facet, a missing layer scale or a facet
taken after RoPE shows up as a large error.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from tiny_models import save_tiny_dinov3
from transformers import AutoModel

from vprflow.models import kinds, loaders
from vprflow.models.vit import load_vit
from vprflow.planning.fingerprints import source_fingerprint

HIDDEN = 32
REGISTERS = 4
PATCH = 16
# Written out here, not imported, so a wrong constant in the module is caught.
IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)
SPREAD = {"scale": 0.3, "skip_norms": False, "bias_offset": 0.5}
# float32 features against float64 hand computations / two float32 runs: see
# tests/models/test_vit.py (measured error ~5e-7 of the largest entry; 1e-5 leaves 10x).
FLOAT32_RTOL = 1e-5


@pytest.fixture(scope="module")
def dinov3_dir(tmp_path_factory):
    return save_tiny_dinov3(
        tmp_path_factory.mktemp("dinov3"),
        hidden_size=HIDDEN,
        registers=REGISTERS,
        image_size=64,
        seed=3,
        **SPREAD,
    )


def _images(count: int, height: int, width: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).random((count, height, width, 3), dtype=np.float32)


def _assert_close(actual: np.ndarray, expected: np.ndarray, rtol: float = FLOAT32_RTOL) -> None:
    scale = float(np.abs(expected).max())
    error = float(np.abs(actual.astype(np.float64) - expected).max())
    assert error <= rtol * scale, f"max error {error:.3g} vs scale {scale:.3g}"


def _reference(model_dir, images: np.ndarray, mean=IMAGENET_MEAN, std=IMAGENET_STD) -> tuple:
    """Hidden states of the untruncated transformers model, preprocessing done here."""
    height, width = images.shape[1:3]
    crop_h, crop_w = height // PATCH * PATCH, width // PATCH * PATCH
    top, left = round((height - crop_h) / 2), round((width - crop_w) / 2)
    crop = images[:, top : top + crop_h, left : left + crop_w]
    pixels = torch.from_numpy((crop - mean) / std).float().permute(0, 3, 1, 2)
    model = AutoModel.from_pretrained(model_dir).eval()
    with torch.no_grad():
        output = model(pixel_values=pixels, output_hidden_states=True)
    return model, output, (crop_h // PATCH, crop_w // PATCH), pixels


def _patches(tokens: torch.Tensor | np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """Drop CLS + registers, reshape to the grid: what the backbone must return."""
    tokens = tokens.double().numpy() if isinstance(tokens, torch.Tensor) else tokens
    assert tokens.shape[1] == 1 + REGISTERS + grid[0] * grid[1]
    return tokens[:, 1 + REGISTERS :].reshape(tokens.shape[0], *grid, -1)


def test_kind_defaults_and_rope():
    kind = kinds.BACKBONES["dinov3"]
    assert kind.defaults["model"] == "facebook/dinov3-vitl16-pretrain-lvd1689m"
    # ViT-L/16 has 24 blocks: 18 (0-based) runs 19 of them, AnyLoc's 32 of 40 in depth.
    assert kind.defaults["layer"] == 18
    assert "pos_embed_interpolation" not in kind.defaults
    assert loaders.LOADERS["features"]["dinov3"] is loaders.LOADERS["features"]["dinov2"]
    assert kind.weights == "model"


def test_shapes_registers_dropped_and_sdpa(dinov3_dir):
    params = {"backbone": "dinov3", "model": str(dinov3_dir), "layer": 1, "facet": "token"}
    backbone = load_vit({**params, "normalize": False}, "cpu")
    assert backbone.patch_size == PATCH and backbone.pos_embed_interpolation is None
    assert backbone.model.config._attn_implementation == "sdpa"
    assert len(backbone.model.model.layer) == 2  # blocks after `layer` are dropped
    images = _images(2, 53, 90, seed=1)  # crop to 48 x 80: 3 x 5 patches
    features = backbone.features(images)
    assert features.shape == (2, 3, 5, HIDDEN) and features.dtype == np.float32
    _, output, grid, _ = _reference(dinov3_dir, images)
    assert grid == (3, 5)
    _assert_close(features, _patches(output.hidden_states[2], grid))


def _rope(states: np.ndarray, cos: np.ndarray, sin: np.ndarray, heads: int) -> np.ndarray:
    """Rotate the patch tokens of ``[B, T, D]`` per head as transformers' DINOv3 does."""
    batch, tokens, dim = states.shape
    split = states.reshape(batch, tokens, heads, dim // heads).copy()
    patches = split[:, 1 + REGISTERS :]
    half = patches.shape[-1] // 2
    rotated = np.concatenate([-patches[..., half:], patches[..., :half]], axis=-1)
    split[:, 1 + REGISTERS :] = patches * cos[None, :, None] + rotated * sin[None, :, None]
    return split.reshape(batch, tokens, dim)


@pytest.mark.parametrize("facet", ["query", "key", "value"])
@pytest.mark.parametrize("layer", [0, -1])
def test_qkv_facets_are_projections_of_normed_input_before_rope(facet, layer, dinov3_dir):
    params = {"backbone": "dinov3", "model": str(dinov3_dir), "layer": layer, "facet": facet}
    images = _images(2, 49, 81, seed=2)  # 3 x 5 patches after the crop
    features = load_vit({**params, "normalize": False}, "cpu").features(images)

    model, output, grid, pixels = _reference(dinov3_dir, images)
    index = layer % model.config.num_hidden_layers
    state = {k: v.double().numpy() for k, v in model.state_dict().items()}
    prefix = f"model.layer.{index}."
    hidden = output.hidden_states[index].double().numpy()  # input of block `index`
    mean, var = hidden.mean(-1, keepdims=True), hidden.var(-1, keepdims=True)
    normed = (hidden - mean) / np.sqrt(var + model.config.layer_norm_eps)
    normed = normed * state[prefix + "norm1.weight"] + state[prefix + "norm1.bias"]
    proj = {"query": "q_proj", "key": "k_proj", "value": "v_proj"}[facet]
    expected = normed @ state[f"{prefix}attention.{proj}.weight"].T
    bias = state.get(f"{prefix}attention.{proj}.bias")
    assert (bias is None) == (facet == "key")  # DINOv3 has no key bias
    if bias is not None:
        expected = expected + bias
    assert features.shape == (2, *grid, HIDDEN)
    _assert_close(features, _patches(expected, grid))

    if facet != "value":  # the rotated projection is something else entirely
        with torch.no_grad():
            cos, sin = (t.double().numpy() for t in model.rope_embeddings(pixels))
        rotated = _rope(expected, cos, sin, model.config.num_attention_heads)
        gap = np.abs(_patches(rotated, grid) - features).max()
        assert gap > 1e-2 * np.abs(features).max()


def test_final_norm_token_is_model_output_and_l2(dinov3_dir):
    params = {"backbone": "dinov3", "model": str(dinov3_dir), "layer": -1, "facet": "token"}
    images = _images(1, 64, 48, seed=4)
    normed = load_vit({**params, "final_norm": True, "normalize": False}, "cpu").features(images)
    _, output, grid, _ = _reference(dinov3_dir, images)
    _assert_close(normed, _patches(output.last_hidden_state, grid))
    unit = load_vit({**params, "final_norm": True}, "cpu").features(images)
    np.testing.assert_allclose(np.linalg.norm(unit, axis=-1), 1.0, atol=1e-5)
    # Two model runs: equal up to float32 rounding (unit vectors, absolute tolerance).
    expected = normed / np.linalg.norm(normed, axis=-1, keepdims=True)
    np.testing.assert_allclose(unit, expected, atol=FLOAT32_RTOL)


def test_mean_std_from_preprocessor_config(dinov3_dir, tmp_path):
    params = {"backbone": "dinov3", "layer": 0, "facet": "token", "normalize": False}
    images = _images(1, 48, 64, seed=5)
    plain = load_vit({**params, "model": str(dinov3_dir)}, "cpu")
    assert plain.mean == pytest.approx(IMAGENET_MEAN) and plain.std == pytest.approx(IMAGENET_STD)

    satellite = tmp_path / "sat"
    shutil.copytree(dinov3_dir, satellite)
    mean, std = [0.430, 0.411, 0.296], [0.213, 0.156, 0.143]  # the sat493m models' values
    processor = {"image_processor_type": "DINOv3ViTImageProcessorFast"}
    processor.update(image_mean=mean, image_std=std)
    (satellite / "preprocessor_config.json").write_text(json.dumps(processor))
    backbone = load_vit({**params, "model": str(satellite)}, "cpu")
    assert backbone.mean == pytest.approx(mean) and backbone.std == pytest.approx(std)
    features = backbone.features(images)
    mean32, std32 = np.array(mean, np.float32), np.array(std, np.float32)
    _, output, grid, _ = _reference(satellite, images, mean32, std32)
    _assert_close(features, _patches(output.hidden_states[1], grid))
    assert np.abs(features - plain.features(images)).max() > 1e-2 * np.abs(features).max()

    (satellite / "preprocessor_config.json").write_text(json.dumps({"image_std": [1, 2]}))
    with pytest.raises(ValueError, match="image_std"):
        load_vit({**params, "model": str(satellite)}, "cpu")


def test_parameter_errors(dinov3_dir, tmp_path):
    base = {"backbone": "dinov3", "model": str(dinov3_dir)}
    with pytest.raises(ValueError, match="layer 18"):  # the ViT-L default on 3 blocks
        load_vit(base, "cpu")
    with pytest.raises(ValueError, match="pos_embed_interpolation does not apply"):
        load_vit({**base, "layer": 0, "pos_embed_interpolation": "original"}, "cpu")
    with pytest.raises(ValueError, match="checkpoint applies to the 'dinov2'"):
        load_vit({**base, "layer": 0, "checkpoint": str(tmp_path / "x.pt")}, "cpu")
    with pytest.raises(ValueError, match="'dinov3_vit' model"):
        load_vit({"backbone": "dinov2", "model": str(dinov3_dir), "layer": 0}, "cpu")


def test_bfloat16_runs_and_stays_close(dinov3_dir):
    params = {"backbone": "dinov3", "model": str(dinov3_dir), "layer": -1}
    images = _images(1, 48, 64, seed=6)
    full = load_vit(params, "cpu").features(images)
    half = load_vit({**params, "dtype": "bfloat16"}, "cpu")
    assert half.model.dtype == torch.bfloat16
    cosine = (full * half.features(images)).sum(-1)  # both unit-normalised
    assert cosine.min() > 0.95


def test_preprocessor_config_is_in_the_key(dinov3_dir, tmp_path):
    directory = tmp_path / "model"
    shutil.copytree(dinov3_dir, directory)
    entry = {**kinds.BACKBONES["dinov3"].defaults, "backbone": "dinov3"}
    entry["model"] = str(directory)
    without = source_fingerprint("features", entry, {}, "backbones.x")
    assert "preprocessor_config.json" not in without
    (directory / "preprocessor_config.json").write_text(json.dumps({"image_mean": [0, 0, 0]}))
    first = source_fingerprint("features", entry, {}, "backbones.x")
    (directory / "preprocessor_config.json").write_text(json.dumps({"image_mean": [1, 0, 0]}))
    second = source_fingerprint("features", entry, {}, "backbones.x")
    assert first["weights"] == second["weights"] == without["weights"]
    assert first["preprocessor_config.json"] != second["preprocessor_config.json"]
    # DINOv2 directories keep their keys: the file is not hashed for them.
    dinov2 = {"backbone": "dinov2", "model": str(directory)}
    assert "preprocessor_config.json" not in source_fingerprint("features", dinov2, {}, "b")
