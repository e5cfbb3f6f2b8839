"""Torch-hub-layout DINOv2 checkpoints (SegVLAD-FineT) loaded into transformers' Dinov2Model.

A random transformers model is written out in the torch-hub layout by the inverse of
the loader's mapping (written independently here), wrapped like the Revisit-Anything
Lightning checkpoint (``state_dict`` with ``backbone.model.`` keys, a NetVLAD head, an
argparse Namespace in ``hyper_parameters``) and saved with ``torch.save``. Loaded on top
of a *different* random model of the same architecture, it must reproduce the original.
"""

from __future__ import annotations

import argparse
import fractions
import re

import numpy as np
import pytest
import torch
from tiny_models import tiny_vit

from vprflow.core.errors import PlanError
from vprflow.models.checkpoints import CheckpointError, load_hub_checkpoint
from vprflow.models.vit import load_vit
from vprflow.planning.fingerprints import source_fingerprint

HIDDEN = 32
SPREAD = {"scale": 0.3, "skip_norms": False, "bias_offset": 0.5}
PREFIX = "backbone.model."
# Two float32 runs of the same weights: see tests/models/test_vit.py (1e-5 of the largest entry).
FLOAT32_RTOL = 1e-5
VARIANTS = {
    "mlp": {},
    "swiglu": {"use_swiglu_ffn": True},
    "registers": {"registers": 4},
}


def to_hub_layout(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    """The torch-hub (facebookresearch/dinov2) state dict of a transformers DINOv2."""
    hub = {}
    for name, tensor in model.state_dict().items():
        tensor = tensor.clone()
        top = {
            "embeddings.cls_token": "cls_token",
            "embeddings.mask_token": "mask_token",
            "embeddings.register_tokens": "register_tokens",
            "embeddings.position_embeddings": "pos_embed",
            "embeddings.patch_embeddings.projection.weight": "patch_embed.proj.weight",
            "embeddings.patch_embeddings.projection.bias": "patch_embed.proj.bias",
            "layernorm.weight": "norm.weight",
            "layernorm.bias": "norm.bias",
        }
        if name in top:
            hub[top[name]] = tensor
            continue
        _, _, index, rest = name.split(".", 3)  # encoder.layer.<i>.<rest>
        block = f"blocks.{index}."
        module, _, kind = rest.rpartition(".")
        if module in ("attention.k_proj", "attention.v_proj", "mlp.up_proj"):
            continue  # fused below with q / gate
        if module == "attention.q_proj":
            parts = [
                model.state_dict()[f"encoder.layer.{index}.attention.{p}_proj.{kind}"]
                for p in "qkv"
            ]
            hub[f"{block}attn.qkv.{kind}"] = torch.cat(parts).clone()
        elif module == "mlp.gate_proj":
            up = model.state_dict()[f"encoder.layer.{index}.mlp.up_proj.{kind}"]
            hub[f"{block}mlp.w12.{kind}"] = torch.cat([tensor, up]).clone()
        else:
            hub_module = {
                "attention.o_proj": "attn.proj",
                "mlp.down_proj": "mlp.w3",
                "layer_scale1": "ls1",
                "layer_scale2": "ls2",
            }.get(module, module)
            hub_kind = "gamma" if kind == "lambda1" else kind
            hub[f"{block}{hub_module}.{hub_kind}"] = tensor
    return hub


def lightning_checkpoint(hub: dict[str, torch.Tensor]) -> dict:
    state = {PREFIX + k: v for k, v in hub.items()}
    state["aggregator.centroids"] = torch.randn(8, HIDDEN)
    state["aggregator.conv.weight"] = torch.randn(8, HIDDEN, 1, 1)
    return {
        "epoch": 3,
        "state_dict": state,
        "hyper_parameters": {"args": argparse.Namespace(clusters_num=8, expName="dnv2_NV")},
    }


@pytest.fixture(scope="module", params=list(VARIANTS))
def case(request, tmp_path_factory):
    """(variant, original model dir, base model dir, checkpoint file)."""
    root = tmp_path_factory.mktemp(request.param)
    options = {"hidden_size": HIDDEN, "image_size": 56, **SPREAD, **VARIANTS[request.param]}
    original = tiny_vit("dinov2", seed=10, **options)
    original.save_pretrained(root / "original")
    tiny_vit("dinov2", seed=11, **options).save_pretrained(root / "base")
    checkpoint = root / "last.ckpt"
    torch.save(lightning_checkpoint(to_hub_layout(original)), checkpoint)
    return request.param, root / "original", root / "base", checkpoint


def _images(count: int, height: int, width: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).random((count, height, width, 3), dtype=np.float32)


def test_hub_checkpoint_reproduces_the_original_model(case):
    _, original, base, checkpoint = case
    # SegVLAD-FineT's features: the last block's tokens after the final norm.
    params = {"backbone": "dinov2", "layer": -1, "facet": "token", "final_norm": True}
    params["normalize"] = False
    images = _images(2, 60, 88, seed=1)
    expected = load_vit({**params, "model": str(original)}, "cpu")
    other = load_vit({**params, "model": str(base)}, "cpu").features(images)
    loaded = load_vit({**params, "model": str(base), "checkpoint": str(checkpoint)}, "cpu")
    reference = expected.model.state_dict()
    for name, tensor in loaded.model.state_dict().items():
        assert torch.equal(tensor, reference[name]), name
    wanted = expected.features(images).astype(np.float64)
    actual = loaded.features(images)
    scale = np.abs(wanted).max()
    assert np.abs(actual - wanted).max() <= FLOAT32_RTOL * scale
    assert np.abs(other - wanted).max() > 1e-2 * scale  # the base model alone differs


def _mlp_case(tmp_path):
    model = tiny_vit("dinov2", hidden_size=HIDDEN, image_size=56, seed=12, **SPREAD)
    model.save_pretrained(tmp_path / "base")
    return model, tmp_path / "base"


@pytest.mark.parametrize("facet", ["query", "key", "value"])
def test_qkv_facets_follow_the_split_qkv(facet, tmp_path):
    model, base = _mlp_case(tmp_path)
    model.save_pretrained(tmp_path / "original")
    other = tiny_vit("dinov2", hidden_size=HIDDEN, image_size=56, seed=13, **SPREAD)
    other.save_pretrained(tmp_path / "other")
    path = tmp_path / "last.ckpt"
    torch.save(lightning_checkpoint(to_hub_layout(model)), path)
    params = {"backbone": "dinov2", "layer": 1, "facet": facet, "normalize": False}
    images = _images(1, 56, 56, seed=2)
    wanted = load_vit({**params, "model": str(tmp_path / "original")}, "cpu").features(images)
    loaded = load_vit({**params, "model": str(tmp_path / "other"), "checkpoint": str(path)}, "cpu")
    actual = loaded.features(images)
    assert np.abs(actual - wanted).max() <= FLOAT32_RTOL * np.abs(wanted).max()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ("drop", r"missing weights of Dinov2Model: encoder\.layer\.1\.layer_scale2\.lambda1"),
        ("extra", r"unexpected keys: backbone\.model\.blocks\.0\.attn\.bogus\.weight"),
        ("shape", r"shapes that differ: embeddings\.position_embeddings \(1, 10, 32\)"),
    ],
)
def test_mismatched_checkpoint_names_file_and_keys(change, message, tmp_path):
    model, base = _mlp_case(tmp_path)
    hub = to_hub_layout(model)
    if change == "drop":
        del hub["blocks.1.ls2.gamma"]
    elif change == "extra":
        hub["blocks.0.attn.bogus.weight"] = torch.zeros(2)
    else:
        hub["pos_embed"] = hub["pos_embed"][:, :10]
    path = tmp_path / "broken.ckpt"
    torch.save(lightning_checkpoint(hub), path)
    params = {"backbone": "dinov2", "model": str(base), "layer": 0, "checkpoint": str(path)}
    with pytest.raises(CheckpointError, match=message) as error:
        load_vit(params, "cpu")
    assert str(path) in str(error.value)


def test_mask_token_may_be_absent_and_plain_state_dicts_load(tmp_path):
    model, base = _mlp_case(tmp_path)
    hub = to_hub_layout(model)
    del hub["mask_token"]  # unused at inference
    path = tmp_path / "plain.pth"
    torch.save(hub, path)  # a bare hub state dict, no prefix, no wrapper
    other = tiny_vit("dinov2", hidden_size=HIDDEN, image_size=56, seed=13, **SPREAD)
    assert load_hub_checkpoint(other, str(path)) == {"prefix": ""}
    for name, tensor in model.state_dict().items():
        if name != "embeddings.mask_token":
            assert torch.equal(other.state_dict()[name], tensor), name


def test_unreadable_checkpoints_are_refused_by_name(tmp_path):
    model, base = _mlp_case(tmp_path)
    params = {"backbone": "dinov2", "model": str(base), "layer": 0}
    unsafe = tmp_path / "unsafe.ckpt"
    checkpoint = lightning_checkpoint(to_hub_layout(model))
    checkpoint["hyper_parameters"]["ratio"] = fractions.Fraction(1, 3)  # not a tensor
    torch.save(checkpoint, unsafe)
    with pytest.raises(CheckpointError, match=r"unsafe\.ckpt.*fractions\.Fraction"):
        load_vit({**params, "checkpoint": str(unsafe)}, "cpu")
    with pytest.raises(CheckpointError, match="does not exist"):
        load_vit({**params, "checkpoint": str(tmp_path / "absent.ckpt")}, "cpu")
    with pytest.raises(CheckpointError, match="is a folder; it must name a file"):
        load_vit({**params, "checkpoint": str(tmp_path)}, "cpu")
    garbage = tmp_path / "garbage.ckpt"
    garbage.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match=r"garbage\.ckpt'?: cannot read it"):
        load_vit({**params, "checkpoint": str(garbage)}, "cpu")
    empty = tmp_path / "empty.ckpt"
    empty.write_bytes(b"")  # torch.load says only "EOFError"
    with pytest.raises(CheckpointError, match=r"empty\.ckpt' is empty \(0 bytes"):
        load_vit({**params, "checkpoint": str(empty)}, "cpu")
    nothing = tmp_path / "nothing.ckpt"
    torch.save({"state_dict": {"aggregator.centroids": torch.zeros(2)}}, nothing)
    with pytest.raises(CheckpointError, match="no DINOv2 weights"):
        load_vit({**params, "checkpoint": str(nothing)}, "cpu")


def test_checkpoint_file_is_hashed_into_the_key(tmp_path):
    path = tmp_path / "last.ckpt"
    torch.save({"state_dict": {"x": torch.zeros(1)}}, path)
    entry = {"backbone": "dinov2", "model": "facebook/dinov2-base", "checkpoint": str(path)}
    first = source_fingerprint("features", entry, {}, "backbones.finet")
    torch.save({"state_dict": {"x": torch.ones(1)}}, path)
    second = source_fingerprint("features", entry, {}, "backbones.finet")
    assert first["weights"] == second["weights"] == "hf:facebook/dinov2-base"
    assert first["checkpoint_sha256"] != second["checkpoint_sha256"]
    plain = source_fingerprint("features", {**entry, "checkpoint": None}, {}, "b")
    assert "checkpoint_sha256" not in plain


@pytest.mark.parametrize(
    ("stage", "entry", "key"),
    [
        ("features", {"backbone": "dinov2", "model": "facebook/dinov2-base"}, "checkpoint"),
        ("features", {"backbone": "import", "patch_size": 14}, "file"),
        ("segments", {"segmenter": "import"}, "file"),
    ],
)
def test_a_weights_or_imported_file_key_naming_a_folder_is_an_error_naming_the_key(
    tmp_path, stage, entry, key
):
    (tmp_path / "last.ckpt").write_bytes(b"weights")
    with pytest.raises(PlanError, match=r"config key where\.(checkpoint|file): .* is a folder"):
        source_fingerprint(stage, {**entry, key: str(tmp_path)}, {}, "where")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(PlanError, match="the folder is empty"):
        source_fingerprint(stage, {**entry, key: str(empty)}, {}, "where")


def test_a_weights_file_or_model_folder_holding_a_link_in_a_loop_names_the_key_and_loop(
    tmp_path,
):
    (tmp_path / "last.ckpt").symlink_to("best.ckpt")
    (tmp_path / "best.ckpt").symlink_to("last.ckpt")
    entry = {"backbone": "dinov2", "model": "facebook/dinov2-base"}
    loop = re.escape(f"{tmp_path / 'last.ckpt'} is a link in a loop (last.ckpt -> best.ckpt")
    with pytest.raises(PlanError, match=rf"config key where\.checkpoint: {loop} -> last.ckpt\)"):
        source_fingerprint(
            "features", {**entry, "checkpoint": str(tmp_path / "last.ckpt")}, {}, "where"
        )
    model = {"backbone": "dinov2", "model": str(tmp_path)}
    with pytest.raises(
        PlanError, match=r"config key where\.model: .*best.ckpt is a link in a loop"
    ):
        source_fingerprint("features", model, {}, "where")
