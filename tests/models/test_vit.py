"""DINOv2 / DINO feature extraction, checked against hand computations on tiny models.

The models are randomly initialised transformers models saved to a temporary directory
(no pretrained weights exist on the test machines). All parameters, LayerNorms and
biases included, are re-drawn with a large spread so that a wrong norm, a swapped
facet or a missing bias shows up as a large error.

The reference forward passes use position embeddings computed here, in float64, from
the rules of the original repositories (``_reference_pos_embed``), unless a test asks
for transformers' own interpolation.
"""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest
import torch
from tiny_models import save_tiny_dino, save_tiny_dinov2
from transformers import AutoModel, ViTModel

from vprflow.core.arrays import center_crop_box
from vprflow.models.vit import load_vit

HIDDEN = 32
# Written out here, not imported, so a wrong constant in the module is caught.
MEAN = np.array([0.485, 0.456, 0.406], np.float32)
STD = np.array([0.229, 0.224, 0.225], np.float32)


# Every parameter, LayerNorms and biases included, re-drawn with a large spread.
SPREAD = {"scale": 0.3, "skip_norms": False, "bias_offset": 0.5}


@pytest.fixture(scope="module")
def dinov2_dir(tmp_path_factory):
    return save_tiny_dinov2(
        tmp_path_factory.mktemp("dinov2"), hidden_size=HIDDEN, image_size=56, seed=0, **SPREAD
    )


@pytest.fixture(scope="module")
def dino_dir(tmp_path_factory):
    return save_tiny_dino(
        tmp_path_factory.mktemp("dino"), hidden_size=HIDDEN, image_size=32, seed=1, **SPREAD
    )


@pytest.fixture(scope="module")
def registers_dir(tmp_path_factory):
    return save_tiny_dinov2(
        tmp_path_factory.mktemp("registers"),
        hidden_size=HIDDEN,
        num_layers=2,
        image_size=56,
        registers=4,
        seed=2,
        **SPREAD,
    )


def _images(count: int, height: int, width: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).random((count, height, width, 3), dtype=np.float32)


def _cubic(distance: float, a: float) -> float:
    """Keys' cubic convolution kernel with parameter ``a``."""
    x = abs(distance)
    if x <= 1:
        return ((a + 2) * x - (a + 3)) * x * x + 1
    if x < 2:
        return ((a * x - 5 * a) * x + 8 * a) * x - 4 * a
    return 0.0


def _bicubic_matrix(size_in: int, size_out: int, scale: float) -> np.ndarray:
    """``[size_out, size_in]`` weights of torch's bicubic (``a = -0.75``, no antialias):
    output ``d`` samples ``s = (d + 0.5) / scale - 0.5`` from taps ``floor(s) - 1 ..
    floor(s) + 2``, indices clamped to the grid."""
    weights = np.zeros((size_out, size_in))
    for d in range(size_out):
        source = (d + 0.5) / scale - 0.5
        base = math.floor(source)
        for k in range(-1, 3):
            index = min(max(base + k, 0), size_in - 1)
            weights[d, index] += _cubic(source - (base + k), -0.75)
    return weights


def _antialias_bicubic_matrix(size_in: int, size_out: int) -> np.ndarray:
    """``[size_out, size_in]`` weights of antialiased bicubic (PIL's filter, ``a = -0.5``):
    the kernel is stretched by the shrink factor, cut at the grid's edges and renormalised."""
    ratio = size_in / size_out
    stretch = max(ratio, 1.0)
    weights = np.zeros((size_out, size_in))
    for d in range(size_out):
        centre = (d + 0.5) * ratio  # continuous coordinates, pixel j spans [j, j + 1)
        row = np.array([_cubic((j + 0.5 - centre) / stretch, -0.5) for j in range(size_in)])
        weights[d] = row / row.sum()
    return weights


def _reference_pos_embed(stored: np.ndarray, rows: int, cols: int, rule: str) -> np.ndarray:
    """Position embeddings ``[1, 1 + rows * cols, D]`` for a ``rows x cols`` patch grid from
    the stored ``[1, 1 + M * M, D]``, float64.

    ``rule``: ``"original"`` (DINO / DINOv2: scale factor ``(n + 0.1) / M`` per axis),
    ``"transformers"`` (scale ``n / M``, i.e. ``size=(rows, cols)``) or ``"registers"``
    (the original DINOv2 ``*_reg`` models: antialiased, ``size=(rows, cols)``).
    """
    side = math.isqrt(stored.shape[1] - 1)
    if (rows, cols) == (side, side):
        return stored
    grid = stored[0, 1:].reshape(side, side, -1)
    if rule == "registers":
        row_weights = _antialias_bicubic_matrix(side, rows)
        col_weights = _antialias_bicubic_matrix(side, cols)
    else:
        offset = {"original": 0.1, "transformers": 0.0}[rule]
        row_weights = _bicubic_matrix(side, rows, (rows + offset) / side)
        col_weights = _bicubic_matrix(side, cols, (cols + offset) / side)
    patches = np.einsum("ri,ijd,cj->rcd", row_weights, grid, col_weights)
    return np.concatenate([stored[:, :1], patches.reshape(1, rows * cols, -1)], axis=1)


def _reference_hidden_states(
    model_dir, images: np.ndarray, patch: int, interpolation: str = "original"
) -> tuple:
    """Hidden states of the untruncated model, with preprocessing done independently.

    ``interpolation="original"`` feeds the model position embeddings from
    :func:`_reference_pos_embed` (the original repositories' rule for its model type);
    ``"transformers"`` leaves the model as transformers builds it.
    """
    height, width = images.shape[1:3]
    crop_h, crop_w = height // patch * patch, width // patch * patch
    top, left = round((height - crop_h) / 2), round((width - crop_w) / 2)  # torchvision's rule
    crop = images[:, top : top + crop_h, left : left + crop_w]
    pixels = (crop - MEAN) / STD
    model = AutoModel.from_pretrained(model_dir).eval()
    if interpolation == "original":
        registers = model.config.model_type == "dinov2_with_registers"
        stored = model.embeddings.position_embeddings.detach().double().numpy()
        rule = "registers" if registers else "original"
        pos = _reference_pos_embed(stored, crop_h // patch, crop_w // patch, rule)
        pos = torch.from_numpy(pos).float()
        model.embeddings.interpolate_pos_encoding = lambda embeddings, height, width: pos
    kwargs = {"interpolate_pos_encoding": True} if isinstance(model, ViTModel) else {}
    with torch.no_grad():
        output = model(
            pixel_values=torch.from_numpy(pixels).permute(0, 3, 1, 2),
            output_hidden_states=True,
            **kwargs,
        )
    grid = (crop_h // patch, crop_w // patch)
    return model, output, grid


# float32 features of these models are within 5e-7 of a float64 run, relative to the
# largest entry (measured for every layer and both kinds, normalised or not), so two float32
# runs with different kernels, threads or weight buffers differ by at most ~1e-6: 1e-5
# leaves 10x. The same bound serves float32 vs float64 hand computations below.
FLOAT32_RTOL = 1e-5


def _assert_close(actual: np.ndarray, expected: np.ndarray, rtol: float = FLOAT32_RTOL) -> None:
    scale = float(np.abs(expected).max())
    error = float(np.abs(actual.astype(np.float64) - expected).max())
    assert error <= rtol * scale, f"max error {error:.3g} vs scale {scale:.3g}"


def test_center_crop_box_matches_torchvision_rounding():
    assert center_crop_box(480, 640, 14) == (2, 5, 476, 630)
    assert center_crop_box(224, 224, 8) == (0, 0, 224, 224)
    # 60 - 56 = 4 -> 2; 101 - 98 = 3 -> round(1.5) = 2 (half to even, like torchvision)
    assert center_crop_box(60, 101, 14) == (2, 2, 56, 98)
    with pytest.raises(ValueError, match="smaller than one"):
        center_crop_box(10, 100, 14)


def test_dinov2_shapes_and_centre_crop(dinov2_dir):
    backbone = load_vit(
        {"backbone": "dinov2", "model": str(dinov2_dir), "layer": 1, "facet": "value"}, "cpu"
    )
    assert backbone.patch_size == 14
    images = _images(2, 60, 101)
    features = backbone.features(images)
    assert features.shape == (2, 4, 7, HIDDEN)
    assert features.dtype == np.float32
    # Centre crop: the pre-cropped region gives the same features, a shifted one does not.
    # (Same pixels, same model: equal up to float32 kernel rounding, see FLOAT32_RTOL.)
    same = backbone.features(images[:, 2:58, 2:100])
    _assert_close(same, features.astype(np.float64), rtol=FLOAT32_RTOL)
    shifted = backbone.features(images[:, 0:56, 0:98])
    assert np.abs(features - shifted).max() > 1e-3


def test_blocks_after_layer_are_dropped(dinov2_dir):
    backbone = load_vit({"backbone": "dinov2", "model": str(dinov2_dir), "layer": 0}, "cpu")
    assert len(backbone.model.encoder.layer) == 1


@pytest.mark.parametrize("facet", ["query", "key", "value"])
@pytest.mark.parametrize("kind", ["dinov2", "dino"])
def test_qkv_facets_match_hand_computation(kind, facet, dinov2_dir, dino_dir):
    model_dir, patch, layer = (dinov2_dir, 14, -2) if kind == "dinov2" else (dino_dir, 8, 0)
    params = {"backbone": kind, "model": str(model_dir), "layer": layer, "facet": facet}
    params["normalize"] = False
    images = _images(2, 45, 71, seed=3)
    features = load_vit(params, "cpu").features(images)

    model, output, (grid_h, grid_w) = _reference_hidden_states(model_dir, images, patch)
    index = layer % model.config.num_hidden_layers
    state = {k: v.double().numpy() for k, v in model.state_dict().items()}
    if kind == "dinov2":
        prefix, norm = f"encoder.layer.{index}.", "norm1"
    else:
        prefix, norm = f"layers.{index}.", "layernorm_before"
    proj = {"query": "q_proj", "key": "k_proj", "value": "v_proj"}[facet]
    hidden = output.hidden_states[index].double().numpy()  # input of block `index`
    mean = hidden.mean(-1, keepdims=True)
    var = hidden.var(-1, keepdims=True)
    normed = (hidden - mean) / np.sqrt(var + model.config.layer_norm_eps)
    normed = normed * state[prefix + norm + ".weight"] + state[prefix + norm + ".bias"]
    weight = state[f"{prefix}attention.{proj}.weight"]
    bias = state[f"{prefix}attention.{proj}.bias"]
    expected = normed @ weight.T + bias
    expected = expected[:, 1:].reshape(2, grid_h, grid_w, -1)
    assert features.shape == expected.shape
    _assert_close(features, expected)


def test_token_facet_is_block_output(dinov2_dir):
    params = {"backbone": "dinov2", "model": str(dinov2_dir), "layer": 1, "facet": "token"}
    images = _images(1, 56, 84, seed=4)
    features = load_vit({**params, "normalize": False}, "cpu").features(images)
    _, output, (grid_h, grid_w) = _reference_hidden_states(dinov2_dir, images, 14)
    expected = output.hidden_states[2][:, 1:].double().numpy().reshape(1, grid_h, grid_w, -1)
    _assert_close(features, expected)


def test_dino_final_norm_and_non_square_input(dino_dir):
    params = {"backbone": "dino", "model": str(dino_dir), "facet": "token", "normalize": False}
    images = _images(2, 43, 75, seed=5)  # not the 32x32 the config was built for
    plain = load_vit(params, "cpu").features(images)
    normed = load_vit({**params, "final_norm": True}, "cpu").features(images)
    assert normed.shape == (2, 5, 9, HIDDEN)
    _, output, _ = _reference_hidden_states(dino_dir, images, 8)
    # The default layer for dino is the last block; with final_norm it is the model output.
    last = output.last_hidden_state[:, 1:].double().numpy().reshape(2, 5, 9, -1)
    _assert_close(normed, last)
    assert np.abs(plain - last).max() > 1e-2


def test_register_tokens_are_dropped(registers_dir):
    params = {"backbone": "dinov2", "model": str(registers_dir), "layer": 0, "facet": "token"}
    images = _images(1, 42, 70, seed=6)
    features = load_vit({**params, "normalize": False}, "cpu").features(images)
    assert features.shape == (1, 3, 5, HIDDEN)
    _, output, _ = _reference_hidden_states(registers_dir, images, 14)
    assert output.hidden_states[1].shape[1] == 1 + 4 + 15
    expected = output.hidden_states[1][:, 5:].double().numpy().reshape(1, 3, 5, -1)
    _assert_close(features, expected)


def test_normalize_gives_unit_patch_norms(dinov2_dir):
    params = {"backbone": "dinov2", "model": str(dinov2_dir), "layer": 2}
    images = _images(2, 56, 56, seed=7)
    raw = load_vit({**params, "normalize": False}, "cpu").features(images)
    unit = load_vit({**params, "normalize": True}, "cpu").features(images)
    norms = np.linalg.norm(unit, axis=-1)
    np.testing.assert_allclose(norms, 1.0, atol=1e-5)
    assert np.abs(np.linalg.norm(raw, axis=-1) - 1.0).max() > 0.1
    # raw and unit come from two model runs: equal only up to FLOAT32_RTOL (unit vectors).
    np.testing.assert_allclose(
        unit, raw / np.linalg.norm(raw, axis=-1, keepdims=True), atol=FLOAT32_RTOL
    )


@pytest.mark.parametrize("kind", ["dinov2", "dino"])
def test_bfloat16_on_cpu_runs_and_stays_close(kind, dinov2_dir, dino_dir):
    model_dir = dinov2_dir if kind == "dinov2" else dino_dir
    params = {"backbone": kind, "model": str(model_dir), "layer": -1, "facet": "value"}
    images = _images(1, 50, 60, seed=8)
    full = load_vit(params, "cpu").features(images)
    half = load_vit({**params, "dtype": "bfloat16"}, "cpu")
    assert half.model.dtype == torch.bfloat16
    reduced = half.features(images)
    assert reduced.dtype == np.float32 and reduced.shape == full.shape
    cosine = (full * reduced).sum(-1)  # both unit-normalised
    assert cosine.min() > 0.95


@pytest.mark.parametrize("dtype", ["float32", "bfloat16"])
@pytest.mark.parametrize("kind", ["dinov2", "dino"])
def test_a_batch_gives_each_image_the_bits_it_gets_alone_on_the_cpu(kind, dtype, request):
    model_dir = request.getfixturevalue(f"{kind}_dir")
    params = {"backbone": kind, "model": str(model_dir), "layer": -1, "dtype": dtype}
    backbone = load_vit(params, "cpu")
    images = _images(4, 50, 60, seed=9)
    alone = np.concatenate([backbone.features(image[None]) for image in images])
    for size in (3, 4):
        batched = [backbone.features(images[i : i + size]) for i in range(0, 4, size)]
        np.testing.assert_array_equal(np.concatenate(batched), alone)


def test_float16_on_cpu_is_refused(dinov2_dir):
    with pytest.raises(ValueError, match="bfloat16"):
        load_vit({"backbone": "dinov2", "model": str(dinov2_dir), "dtype": "float16"}, "cpu")


def test_parameter_errors(dinov2_dir, dino_dir):
    base = {"backbone": "dinov2", "model": str(dinov2_dir)}
    with pytest.raises(ValueError, match="layer 31"):  # the ViT-G default on a 3-block model
        load_vit(base, "cpu")
    with pytest.raises(ValueError, match="out of range"):
        load_vit({**base, "layer": -4}, "cpu")
    with pytest.raises(ValueError, match="facet"):
        load_vit({**base, "layer": 0, "facet": "attn"}, "cpu")
    with pytest.raises(ValueError, match="final_norm"):
        load_vit({**base, "layer": 0, "facet": "value", "final_norm": True}, "cpu")
    with pytest.raises(ValueError, match="'vit'"):
        load_vit({"backbone": "dinov2", "model": str(dino_dir), "layer": 0}, "cpu")
    with pytest.raises(ValueError, match="backbone"):
        load_vit({"backbone": "resnet", "model": str(dino_dir)}, "cpu")
    with pytest.raises(ValueError, match="pos_embed_interpolation 'bilinear'"):
        load_vit({**base, "layer": 0, "pos_embed_interpolation": "bilinear"}, "cpu")
    backbone = load_vit({**base, "layer": 0}, "cpu")
    with pytest.raises(ValueError, match=r"\[B, H, W, 3\]"):
        backbone.features(np.zeros((56, 56, 3), np.float32))
    with pytest.raises(ValueError, match="smaller than one"):
        backbone.features(np.zeros((1, 13, 56, 3), np.float32))


# ------------------------------------------------- position-embedding interpolation

# (model fixture, patch side, blocks); both tiny models store a 4 x 4 grid (M = 4).
_KINDS = {"dinov2": ("dinov2_dir", 14, 3), "dino": ("dino_dir", 8, 2)}


def _model_dir(kind: str, request) -> object:
    return request.getfixturevalue(_KINDS[kind][0])


def _interpolated(backbone, rows: int, cols: int) -> torch.Tensor:
    """The backbone model's position embeddings for a ``rows x cols`` patch input."""
    patch = backbone.patch_size
    tokens = torch.zeros(1, 1 + rows * cols, HIDDEN)
    with torch.no_grad():
        return backbone.model.embeddings.interpolate_pos_encoding(
            tokens, rows * patch, cols * patch
        )


@pytest.mark.parametrize("grid", [(5, 7), (7, 5), (3, 5), (2, 9), (6, 6)])
@pytest.mark.parametrize("kind", ["dinov2", "dino"])
def test_original_pos_embed_interpolation_matches_formula(kind, grid, request):
    params = {"backbone": kind, "model": str(_model_dir(kind, request)), "layer": 0}
    backbone = load_vit(params, "cpu")
    assert backbone.pos_embed_interpolation == "original"
    stored = backbone.model.embeddings.position_embeddings.detach().double().numpy()
    actual = _interpolated(backbone, *grid).numpy()
    expected = _reference_pos_embed(stored, *grid, "original")
    assert actual.shape == expected.shape == (1, 1 + grid[0] * grid[1], HIDDEN)
    _assert_close(actual, expected)  # float32 interpolation against float64: rtol 1e-5
    # The 0.1 offset moves the samples: transformers' rule is far outside that tolerance.
    other = _reference_pos_embed(stored, *grid, "transformers")
    assert np.abs(other - expected).max() > 1e-3 * np.abs(expected).max()
    transformers_rule = load_vit({**params, "pos_embed_interpolation": "transformers"}, "cpu")
    _assert_close(_interpolated(transformers_rule, *grid).numpy(), other)


@pytest.mark.parametrize("interpolation", ["original", "transformers"])
@pytest.mark.parametrize("kind", ["dinov2", "dino"])
def test_square_input_with_stored_grid_uses_stored_embeddings(kind, interpolation, request):
    model_dir = str(_model_dir(kind, request))
    params = {"backbone": kind, "model": model_dir, "layer": 0}
    backbone = load_vit({**params, "pos_embed_interpolation": interpolation}, "cpu")
    assert _interpolated(backbone, 4, 4) is backbone.model.embeddings.position_embeddings
    patch = backbone.patch_size
    images = _images(1, 4 * patch, 4 * patch, seed=11)
    model = AutoModel.from_pretrained(model_dir).eval()  # unpatched, the stored grid as is
    kwargs = {"interpolate_pos_encoding": True} if isinstance(model, ViTModel) else {}
    with torch.no_grad():
        output = model(
            pixel_values=torch.from_numpy((images - MEAN) / STD).permute(0, 3, 1, 2),
            output_hidden_states=True,
            **kwargs,
        )
    features = load_vit({**params, "facet": "token", "normalize": False}, "cpu").features(images)
    expected = output.hidden_states[1][:, 1:].double().numpy().reshape(1, 4, 4, -1)
    _assert_close(features, expected)


@pytest.mark.parametrize("kind", ["dinov2", "dino"])
def test_pos_embed_interpolation_options_give_their_forward_passes(kind, request):
    """ "original" features equal a forward pass with the reference embeddings,
    "transformers" features equal the unmodified transformers model, and they differ."""
    model_dir = _model_dir(kind, request)
    _, patch, blocks = _KINDS[kind]
    params = {"backbone": kind, "model": str(model_dir), "layer": -1, "facet": "token"}
    params["normalize"] = False
    images = _images(2, 5 * patch + 3, 7 * patch + 2, seed=12)  # 5 x 7 patches after the crop
    features = {}
    for interpolation in ("original", "transformers"):
        backbone = load_vit({**params, "pos_embed_interpolation": interpolation}, "cpu")
        features[interpolation] = backbone.features(images)
        _, output, grid = _reference_hidden_states(model_dir, images, patch, interpolation)
        assert grid == (5, 7)
        expected = output.hidden_states[blocks][:, 1:].double().numpy().reshape(2, 5, 7, -1)
        _assert_close(features[interpolation], expected)  # rtol 1e-5 of the largest value
    difference = np.abs(features["original"] - features["transformers"]).max()
    assert difference > 1e-3 * np.abs(features["transformers"]).max()


def test_registers_models_keep_transformers_interpolation(registers_dir):
    # The original DINOv2 *_reg models interpolate antialiased to the output size, as
    # transformers' Dinov2WithRegistersEmbeddings does: "original" keeps that method.
    params = {"backbone": "dinov2", "model": str(registers_dir), "layer": 0, "facet": "token"}
    images = _images(1, 42, 98, seed=13)  # 3 x 7 patches
    original = load_vit(params, "cpu")
    assert "interpolate_pos_encoding" not in vars(original.model.embeddings)
    stored = original.model.embeddings.position_embeddings.detach().double().numpy()
    for grid in ((3, 7), (5, 6), (6, 6)):
        expected = _reference_pos_embed(stored, *grid, "registers")
        _assert_close(_interpolated(original, *grid).numpy(), expected)
    plain = load_vit({**params, "pos_embed_interpolation": "transformers"}, "cpu")
    np.testing.assert_array_equal(original.features(images), plain.features(images))


# transformers >= 5 renamed the attention / MLP weights; checkpoints on the hub (e.g.
# facebook/dinov2-giant, facebook/dino-vitb8) still use the old names. (new, old) pairs:
_LEGACY_NAMES = {
    "dinov2": [
        (".attention.q_proj.", ".attention.attention.query."),
        (".attention.k_proj.", ".attention.attention.key."),
        (".attention.v_proj.", ".attention.attention.value."),
        (".attention.o_proj.", ".attention.output.dense."),
    ],
    "dino": [
        ("layers.", "encoder.layer."),
        (".attention.q_proj.", ".attention.attention.query."),
        (".attention.k_proj.", ".attention.attention.key."),
        (".attention.v_proj.", ".attention.attention.value."),
        (".attention.o_proj.", ".attention.output.dense."),
        (".mlp.fc1.", ".intermediate.dense."),
        (".mlp.fc2.", ".output.dense."),
    ],
}


def _write_legacy_checkpoint(source, target, kind: str, drop: str | None = None) -> None:
    from safetensors.torch import load_file, save_file

    target.mkdir()
    shutil.copy(source / "config.json", target / "config.json")
    renamed = {}
    for name, tensor in load_file(source / "model.safetensors").items():
        for new, old in _LEGACY_NAMES[kind]:
            name = old + name[len(new) :] if name.startswith(new) else name.replace(new, old)
        renamed[name] = tensor
    assert any("attention.attention.query" in name for name in renamed)
    if drop is not None:
        del renamed[drop]
    save_file(renamed, target / "model.safetensors", metadata={"format": "pt"})


@pytest.mark.parametrize("kind", ["dinov2", "dino"])
def test_legacy_hub_checkpoint_names_load_the_same_weights(kind, dinov2_dir, dino_dir, tmp_path):
    model_dir = dinov2_dir if kind == "dinov2" else dino_dir
    legacy = tmp_path / "legacy"
    _write_legacy_checkpoint(model_dir, legacy, kind)
    params = {"backbone": kind, "layer": 0, "facet": "value", "normalize": False}
    images = _images(1, 56, 56, seed=9)
    reference = load_vit({**params, "model": str(model_dir)}, "cpu")
    loaded = load_vit({**params, "model": str(legacy)}, "cpu")
    # The same weights, bit for bit; features equal up to float32 kernel rounding (the
    # weights sit in other buffers, which may pick other BLAS code paths).
    expected_state = reference.model.state_dict()
    assert loaded.model.state_dict().keys() == expected_state.keys()
    for name, tensor in loaded.model.state_dict().items():
        assert torch.equal(tensor, expected_state[name]), name
    expected = reference.features(images)
    _assert_close(loaded.features(images), expected.astype(np.float64))


def test_checkpoint_missing_weights_is_an_error(dinov2_dir, tmp_path):
    broken = tmp_path / "broken"
    _write_legacy_checkpoint(
        dinov2_dir, broken, "dinov2", drop="encoder.layer.0.attention.attention.value.weight"
    )
    with pytest.raises(ValueError, match="lacks 1 weights"):
        load_vit({"backbone": "dinov2", "model": str(broken), "layer": 0}, "cpu")
