"""MegaLoc (vprflow.models.trained.megaloc) against float64 formulas, loaded through its
real loader from random weights saved in both published layouts: ``model.safetensors``
(``backbone.<torch-hub DINOv2>`` without ``mask_token``, ``aggregator.agg.*``,
``aggregator.linear.*``) and the older ``megaloc.torch`` (``backbone.model.*``), with a
tiny 2-block ViT."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from safetensors.torch import save_file
from torch.nn import functional as F
from trained_references import prefixed, randomise, salad_reference, tiny_config, vit_reference

from vprflow.models.checkpoints import CheckpointError
from vprflow.models.kinds import trained_model
from vprflow.models.trained.megaloc import MegaLoc, MegaLocHead, load_megaloc
from vprflow.models.trunks.dinov2 import dinov2_hub_state_dict

MEGALOC_URL = trained_model("megaloc").published().url

SIZES = {"feat_dim": 24, "num_clusters": 4, "cluster_dim": 8, "token_dim": 16, "mlp_dim": 20}


def _images(height: int = 70, width: int = 84, seed: int = 0) -> torch.Tensor:
    return torch.randn(2, 3, height, width, generator=torch.Generator().manual_seed(seed))


def _checkpoint(model: MegaLoc, backbone_prefix: str = "backbone.") -> dict[str, torch.Tensor]:
    hub = dinov2_hub_state_dict(model.backbone)
    if backbone_prefix == "backbone.":
        hub.pop("mask_token")  # MegaLoc's own ViT has no mask token
    state = prefixed(hub, backbone_prefix)
    state.update(prefixed(model.aggregator.state_dict(), "aggregator."))
    return state


def megaloc_reference(source: MegaLoc, images: torch.Tensor) -> torch.Tensor:
    """Float64: DINOv2 with final norm, SALAD's aggregation, ``linear``, L2."""
    patches, cls = vit_reference(dinov2_hub_state_dict(source.backbone), images, heads=2)
    agg = {
        k[len("agg.") :]: v
        for k, v in source.aggregator.state_dict().items()
        if k.startswith("agg.")
    }
    salad = salad_reference(agg, patches, cls)
    linear = source.aggregator.linear
    out = salad @ linear.weight.detach().double().T + linear.bias.detach().double()
    return F.normalize(out, dim=1)


@pytest.fixture
def source():
    return randomise(MegaLoc(tiny_config(), **SIZES), seed=1)


def test_safetensors_checkpoint_matches_float64_reference(source, tmp_path):
    path = tmp_path / "model.safetensors"
    save_file(_checkpoint(source), str(path))
    model = load_megaloc(str(path), tiny_config(), **SIZES)
    images = _images()
    with torch.no_grad():
        got = model(images)
    assert got.shape == (2, 24)
    np.testing.assert_allclose(got, megaloc_reference(source, images).float(), rtol=0, atol=2e-6)
    np.testing.assert_allclose(got.norm(dim=1), 1.0, atol=1e-6)


def test_older_torch_release_layout_loads(source, tmp_path):
    path = tmp_path / "megaloc.torch"
    torch.save(_checkpoint(source, "backbone.model."), path)
    model = load_megaloc(str(path), tiny_config(), **SIZES)
    with torch.no_grad():
        np.testing.assert_array_equal(model(_images()), source(_images()))


def test_sides_off_the_patch_grid_are_resized_like_megaloc(source):
    images = _images(60, 80)  # round(60 / 14) * 14 = 56, round(80 / 14) * 14 = 84
    resized = F.interpolate(images, size=(56, 84), mode="bilinear", antialias=True)
    with torch.no_grad():
        np.testing.assert_array_equal(source(images), source(resized))
        assert source.feature_map(images).shape == (2, 32, 4, 6)
    np.testing.assert_allclose(
        source(images).detach(), megaloc_reference(source, resized).float(), atol=2e-6
    )


def test_published_sizes():
    head = MegaLocHead(768)
    shapes = {k: tuple(v.shape) for k, v in head.state_dict().items()}
    assert head.agg.dim == 64 * 256 + 256 == 16640
    assert shapes["linear.weight"] == (8448, 16640)
    assert shapes["agg.cluster_features.3.weight"] == (256, 512, 1, 1)
    assert shapes["agg.score.3.weight"] == (64, 512, 1, 1)


def test_missing_file_names_model_file_and_url(tmp_path):
    path = tmp_path / "model.safetensors"
    with pytest.raises(CheckpointError) as error:
        load_megaloc(str(path), tiny_config(), **SIZES)
    message = str(error.value)
    assert "MegaLoc" in message and str(path) in message and MEGALOC_URL in message


def test_mismatched_checkpoint_names_the_key(source, tmp_path):
    state = _checkpoint(source)
    del state["aggregator.linear.bias"]
    save_file(state, str(tmp_path / "model.safetensors"))
    with pytest.raises(CheckpointError, match=r"aggregator\.linear\.bias"):
        load_megaloc(str(tmp_path / "model.safetensors"), tiny_config(), **SIZES)
    state = _checkpoint(source)
    del state["backbone.norm.weight"]
    save_file(state, str(tmp_path / "b.safetensors"))
    with pytest.raises(CheckpointError, match=r"backbone\.norm\.weight"):
        load_megaloc(str(tmp_path / "b.safetensors"), tiny_config(), **SIZES)
    (tmp_path / "c.safetensors").write_bytes(b"not safetensors")
    with pytest.raises(CheckpointError, match="safetensors"):
        load_megaloc(str(tmp_path / "c.safetensors"), tiny_config(), **SIZES)
