"""VLAD-BuFF (vprflow.models.trained.vlad_buff) against float64 formulas, loaded through
its real checkpoint loader from random weights saved in the published layout
(``{num_pcs, state_dict}``: ``backbone.model.<torch-hub DINOv2>``, ``aggregator.*``,
``WPCA_<n>.0.*``), on a tiny 2-block ViT."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from trained_references import (
    prefixed,
    randomise,
    tiny_config,
    vit_reference,
    vlad_buff_reference,
    whitening_reference,
)

from vprflow.models.checkpoints import CheckpointError
from vprflow.models.kinds import VLAD_BUFF_RELEASE, vlad_buff_file
from vprflow.models.trained.vlad_buff import VladBuff, VladBuffAggregator, load_vlad_buff
from vprflow.models.trunks.dinov2 import dinov2_hub_state_dict

SIZES = {"nv_pca": 6, "num_pcs": 10, "num_clusters": 4}
# Float32 model against a float64 formula: descriptor entries are O(0.1).
FLOAT32_ATOL = 2e-6


def _images(height: int = 70, width: int = 84, count: int = 2, seed: int = 0) -> torch.Tensor:
    return torch.randn(count, 3, height, width, generator=torch.Generator().manual_seed(seed))


def _sharpen(model: VladBuff) -> VladBuff:
    """Trained-like: a sharp soft assignment, AntiBurst at its initial (8, 7, 1)."""
    with torch.no_grad():
        model.aggregator.conv.weight.mul_(10.0)
        model.aggregator.ab_params.copy_(torch.tensor([8.0, 7.0, 1.0]))
    return model


def _checkpoint(model: VladBuff, whitening: str = "WPCA_10.") -> dict:
    """As add_pca.py saves it: the whitening under ``WPCA_<n>`` in float64."""
    state = prefixed(dinov2_hub_state_dict(model.backbone), "backbone.model.")
    state.update(prefixed(model.aggregator.state_dict(), "aggregator."))
    state.update({k: v.double() for k, v in prefixed(model.WPCA.state_dict(), whitening).items()})
    return {"num_pcs": model.num_pcs, "state_dict": state}


@pytest.fixture
def saved(tmp_path):
    source = _sharpen(randomise(VladBuff(tiny_config(), **SIZES), seed=1))
    path = tmp_path / vlad_buff_file(6, 10)
    torch.save(_checkpoint(source), path)
    return source, path


@pytest.mark.parametrize("nv_pca", [None, 5])
def test_aggregator_matches_float64_formula(nv_pca):
    aggregator = randomise(VladBuffAggregator(16, num_clusters=3, nv_pca=nv_pca), 3)
    with torch.no_grad():
        aggregator.ab_params.copy_(torch.tensor([8.0, 7.0, 1.3]))
    x = torch.randn(2, 16, 3, 4, generator=torch.Generator().manual_seed(4))
    got = aggregator.double()(x.double())
    expected = vlad_buff_reference(aggregator.state_dict(), x)
    assert got.shape == (2, 3 * (nv_pca or 16))
    np.testing.assert_allclose(got.detach().numpy(), expected.numpy(), rtol=0, atol=1e-12)


def test_a_burst_of_one_patch_counts_about_once():
    """Burstiness: among dissimilar patches (orthogonal: ``s_ij = -2``, sigmoid(-9) ~ 1e-4),
    a patch repeated 5 times gets the burst weight ~5 per copy, so the VLAD is nearly
    that of the patch seen once; plain NetVLAD (every weight equal) counts it 5 times."""
    aggregator = randomise(VladBuffAggregator(4, num_clusters=2), 5)
    basis = torch.eye(4)[:, :3]  # three orthogonal patches as a 1 x 3 map
    burst = torch.cat([basis[:, :1].repeat(1, 5), basis[:, 1:]], dim=1)  # the first x 5
    with torch.no_grad():
        aggregator.ab_params.copy_(torch.tensor([8.0, 7.0, 1.0]))
        once = aggregator(basis[None, :, None, :])
        repeated = aggregator(burst[None, :, None, :])
        aggregator.ab_params.copy_(torch.tensor([0.0, 0.0, 1.0]))  # equal weights
        plain_once = aggregator(basis[None, :, None, :])
        plain_repeated = aggregator(burst[None, :, None, :])
    assert float((repeated - once).abs().max()) < 2e-3
    assert float((plain_repeated - plain_once).abs().max()) > 0.05


def test_published_sizes():
    assert VladBuffAggregator(768).dim == 64 * 768 == 49152
    with_pca = VladBuffAggregator(768, nv_pca=192)
    assert with_pca.dim == 64 * 192 == 12288
    shapes = {k: tuple(v.shape) for k, v in with_pca.state_dict().items()}
    assert shapes == {
        "pca_mean": (768,),
        "pca_rot": (192, 768),
        "conv.weight": (64, 192, 1, 1),
        "centroids": (64, 192),
        "ab_params": (3,),
    }
    assert vlad_buff_file(None) == "dnv2_NV_AB_wpca8192_last.ckpt"
    assert vlad_buff_file(192) == "dnv2_NV_192PCA_AB_wpca4096_last.ckpt"


def test_loaded_checkpoint_matches_float64_reference(saved):
    source, path = saved
    model = load_vlad_buff(str(path), tiny_config(), **SIZES)
    images = _images()  # 5 x 6 patches: the 4 x 4 stored grid is interpolated
    hub = dinov2_hub_state_dict(source.backbone)
    patches, _ = vit_reference(hub, images, heads=2)
    vlad = vlad_buff_reference(source.aggregator.state_dict(), patches)
    conv = source.WPCA.state_dict()
    expected = whitening_reference(conv["0.weight"], conv["0.bias"], vlad)
    with torch.no_grad():
        got = model(images)
        np.testing.assert_allclose(model.feature_map(images), patches.float(), atol=1e-4)
    assert got.shape == (2, 10)
    np.testing.assert_allclose(got.numpy(), expected.float().numpy(), rtol=0, atol=FLOAT32_ATOL)
    np.testing.assert_allclose(got.norm(dim=1).numpy(), 1.0, atol=1e-6)
    # Without the whitening, the same file gives the VLAD before it.
    bare = load_vlad_buff(str(path), tiny_config(), **{**SIZES, "num_pcs": None})
    with torch.no_grad():
        got = bare(images)
    assert got.shape == (2, 4 * 6)
    np.testing.assert_allclose(got.numpy(), vlad.float().numpy(), rtol=0, atol=FLOAT32_ATOL)


def test_loader_replaces_every_weight(saved):
    source, path = saved
    model = load_vlad_buff(str(path), tiny_config(), **SIZES)
    images = _images(56, 56)
    with torch.no_grad():
        np.testing.assert_array_equal(model(images).numpy(), source(images).numpy())


def test_hubconf_renamed_whitening_loads_and_other_whitenings_are_ignored(saved, tmp_path):
    """hubconf.py renames WPCA_<n>. to WPCA.; add_pca.py may leave a second whitening of
    another size in the file, which the authors' loaders drop."""
    source, _ = saved
    checkpoint = _checkpoint(source, whitening="WPCA.")
    checkpoint["state_dict"]["WPCA_4.0.weight"] = torch.zeros(4, 24, 1, 1, dtype=torch.float64)
    checkpoint["state_dict"]["loss_fn.distance.scale"] = torch.ones(1)
    torch.save(checkpoint, tmp_path / "renamed.ckpt")
    model = load_vlad_buff(str(tmp_path / "renamed.ckpt"), tiny_config(), **SIZES)
    with torch.no_grad():
        np.testing.assert_array_equal(model(_images()).numpy(), source(_images()).numpy())


def test_missing_file_names_model_file_and_url(tmp_path):
    path = tmp_path / "absent.ckpt"
    with pytest.raises(CheckpointError) as error:
        load_vlad_buff(str(path), tiny_config(), **SIZES)
    message = str(error.value)
    assert "VLAD-BuFF" in message and str(path) in message
    assert VLAD_BUFF_RELEASE + vlad_buff_file(6, 10) in message


@pytest.mark.parametrize(
    ("change", "named"),
    [
        (lambda s: s.pop("aggregator.ab_params"), "aggregator.ab_params"),
        (lambda s: s.pop("backbone.model.blocks.1.attn.proj.bias"), "attn.proj.bias"),
        (lambda s: s.update({"aggregator.extra.weight": torch.zeros(1)}), "aggregator.extra"),
        (lambda s: s.update({"head.extra": torch.zeros(1)}), "head.extra"),
        (lambda s: s.pop("WPCA_10.0.bias"), "WPCA_10.0.bias"),
        (
            lambda s: s.update({"WPCA_10.0.weight": torch.zeros(10, 25, 1, 1)}),
            "WPCA_10.0.weight",
        ),
        (
            lambda s: s.update({"aggregator.centroids": torch.zeros(5, 6)}),
            "aggregator.centroids",
        ),
    ],
)
def test_mismatched_checkpoint_names_the_key(saved, tmp_path, change, named):
    source, _ = saved
    checkpoint = _checkpoint(source)
    change(checkpoint["state_dict"])
    path = tmp_path / "bad.ckpt"
    torch.save(checkpoint, path)
    with pytest.raises(CheckpointError) as error:
        load_vlad_buff(str(path), tiny_config(), **SIZES)
    assert named in str(error.value) and VLAD_BUFF_RELEASE in str(error.value)


def test_a_file_without_the_asked_whitening_names_the_ones_it_has(saved):
    _, path = saved
    with pytest.raises(CheckpointError, match=r"no whitening of 12 dims.*WPCA_10\."):
        load_vlad_buff(str(path), tiny_config(), **{**SIZES, "num_pcs": 12})


def test_the_other_published_model_is_refused_naming_its_keys(saved):
    """A checkpoint with pre-pool PCA read as the one without: its PCA keys are named."""
    _, path = saved
    with pytest.raises(CheckpointError, match=r"aggregator\.pca_mean") as error:
        load_vlad_buff(str(path), tiny_config(), **{**SIZES, "nv_pca": None})
    assert "dnv2_NV_AB_wpca10_last.ckpt" in str(error.value)
