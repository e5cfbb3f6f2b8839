"""SALAD (vprflow.models.trained.salad) against float64 formulas, loaded through its real
checkpoint loader from random weights saved in the ``dino_salad.ckpt`` layout
(``backbone.model.<torch-hub DINOv2>``, ``aggregator.*``), on a tiny 2-block ViT."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from trained_references import (
    prefixed,
    randomise,
    salad_reference,
    sinkhorn_reference,
    tiny_config,
    vit_reference,
)

from vprflow.models.checkpoints import CheckpointError
from vprflow.models.kinds import trained_model
from vprflow.models.trained.salad import SALAD, SaladAggregator, load_salad, sinkhorn_log
from vprflow.models.trunks.dinov2 import dinov2_hub_state_dict

SALAD_URL = trained_model("salad").published().url

SIZES = {"num_clusters": 4, "cluster_dim": 8}
# Float32 model against a float64 formula: descriptor entries are O(0.1).
FLOAT32_ATOL = 2e-6


def _images(height: int = 70, width: int = 84, count: int = 2, seed: int = 0) -> torch.Tensor:
    return torch.randn(count, 3, height, width, generator=torch.Generator().manual_seed(seed))


def _checkpoint(model: SALAD) -> dict[str, torch.Tensor]:
    state = prefixed(dinov2_hub_state_dict(model.backbone), "backbone.model.")
    state.update(prefixed(model.aggregator.state_dict(), "aggregator."))
    return state


@pytest.fixture
def saved(tmp_path):
    source = randomise(SALAD(tiny_config(), **SIZES), seed=1)
    path = tmp_path / "dino_salad.ckpt"
    torch.save(_checkpoint(source), path)
    return source, path


def test_sinkhorn_matches_float64_iterations():
    scores = torch.randn(3, 5, 12, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    dust_bin = torch.tensor(0.7, dtype=torch.float64)
    for iterations in (1, 3, 7):
        plan = sinkhorn_log(scores, dust_bin, iterations)
        for b in range(3):
            expected = sinkhorn_reference(scores[b].numpy(), 0.7, iterations)
            np.testing.assert_allclose(plan[b].numpy(), expected, rtol=0, atol=1e-12)
    # After the last column update each patch spreads a mass of exactly 1.
    np.testing.assert_allclose(plan.exp().sum(dim=1).numpy(), 1.0, atol=1e-12)


def test_aggregator_matches_float64_formula():
    aggregator = randomise(SaladAggregator(16, num_clusters=5, cluster_dim=6, token_dim=7), 3)
    x = torch.randn(2, 16, 3, 4, generator=torch.Generator().manual_seed(4))
    t = torch.randn(2, 16, generator=torch.Generator().manual_seed(5))
    got = aggregator.double()(x.double(), t.double())
    expected = salad_reference(aggregator.state_dict(), x, t)
    assert got.shape == (2, 7 + 6 * 5)
    np.testing.assert_allclose(got.detach().numpy(), expected.numpy(), rtol=0, atol=1e-12)


def test_published_sizes():
    aggregator = SaladAggregator(768)
    assert aggregator.dim == 8448
    shapes = {k: tuple(v.shape) for k, v in aggregator.state_dict().items()}
    assert shapes["score.3.weight"] == (64, 512, 1, 1)
    assert shapes["cluster_features.3.weight"] == (128, 512, 1, 1)
    assert shapes["token_features.2.weight"] == (256, 512)
    assert shapes["dust_bin"] == ()


def test_loaded_checkpoint_matches_float64_reference(saved):
    source, path = saved
    model = load_salad(str(path), tiny_config(), **SIZES)
    images = _images()  # 5 x 6 patches: the 4 x 4 stored grid is interpolated
    hub = dinov2_hub_state_dict(source.backbone)
    patches, cls = vit_reference(hub, images, heads=2)
    expected = salad_reference(source.aggregator.state_dict(), patches, cls)
    with torch.no_grad():
        got = model(images)
        np.testing.assert_allclose(model.feature_map(images), patches.float(), atol=1e-4)
    assert got.shape == (2, 256 + 8 * 4)
    np.testing.assert_allclose(got.numpy(), expected.float().numpy(), rtol=0, atol=FLOAT32_ATOL)
    np.testing.assert_allclose(got.norm(dim=1).numpy(), 1.0, atol=1e-6)


def test_loader_replaces_every_weight(saved):
    source, path = saved
    model = load_salad(str(path), tiny_config(), **SIZES)
    images = _images(56, 56)
    with torch.no_grad():
        np.testing.assert_array_equal(model(images).numpy(), source(images).numpy())


def test_missing_file_names_model_file_and_url(tmp_path):
    path = tmp_path / "absent.ckpt"
    with pytest.raises(CheckpointError) as error:
        load_salad(str(path), tiny_config(), **SIZES)
    message = str(error.value)
    assert "SALAD" in message and str(path) in message and SALAD_URL in message


@pytest.mark.parametrize(
    ("change", "named"),
    [
        (lambda s: s.pop("aggregator.dust_bin"), "aggregator.dust_bin"),
        (lambda s: s.pop("backbone.model.blocks.1.attn.proj.bias"), "attn.proj.bias"),
        (lambda s: s.update({"aggregator.extra.weight": torch.zeros(1)}), "aggregator.extra"),
        (
            lambda s: s.update({"aggregator.score.3.weight": torch.zeros(5, 512, 1, 1)}),
            "aggregator.score.3.weight",
        ),
    ],
)
def test_mismatched_checkpoint_names_the_key(saved, tmp_path, change, named):
    source, _ = saved
    state = _checkpoint(source)
    change(state)
    path = tmp_path / "bad.ckpt"
    torch.save(state, path)
    with pytest.raises(CheckpointError) as error:
        load_salad(str(path), tiny_config(), **SIZES)
    assert named in str(error.value) and SALAD_URL in str(error.value)


def test_other_backbone_prefix_is_refused(saved, tmp_path):
    source, _ = saved
    state = {
        k.replace("backbone.model.", "backbone.dino."): v for k, v in _checkpoint(source).items()
    }
    path = tmp_path / "boq_like.pth"
    torch.save(state, path)
    with pytest.raises(CheckpointError, match="backbone.dino."):
        load_salad(str(path), tiny_config(), **SIZES)


def test_lightning_state_dict_is_unwrapped(saved, tmp_path):
    source, _ = saved
    path = tmp_path / "lightning.ckpt"
    torch.save({"state_dict": _checkpoint(source), "epoch": 3}, path)
    model = load_salad(str(path), tiny_config(), **SIZES)
    with torch.no_grad():
        np.testing.assert_array_equal(model(_images()).numpy(), source(_images()).numpy())


def test_training_loss_keys_are_ignored_others_are_not(saved, tmp_path):
    source, _ = saved
    state = _checkpoint(source)
    state["loss_fn.distance.scale"] = torch.ones(1)
    torch.save(state, tmp_path / "loss.ckpt")
    model = load_salad(str(tmp_path / "loss.ckpt"), tiny_config(), **SIZES)
    with torch.no_grad():
        np.testing.assert_array_equal(model(_images()).numpy(), source(_images()).numpy())
    state["head.extra"] = torch.ones(1)
    torch.save(state, tmp_path / "extra.ckpt")
    with pytest.raises(CheckpointError, match=r"head\.extra"):
        load_salad(str(tmp_path / "extra.ckpt"), tiny_config(), **SIZES)
