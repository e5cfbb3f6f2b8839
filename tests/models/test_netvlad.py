"""NetVLAD (vprflow.models.trained.netvlad) against the float64 NetVLAD formula, loaded
through its real loader from random weights saved in the Patch-NetVLAD /
pytorch-NetVlad checkpoint layout (``{"state_dict": {encoder.*, pool.centroids,
pool.conv.weight, WPCA.0.*}, ...}``), with a one-convolution encoder and 4 clusters."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from trained_references import randomise

from vprflow.models.checkpoints import CheckpointError
from vprflow.models.trained.netvlad import (
    DEFAULT_VARIANT,
    VARIANTS,
    NetVLADModel,
    NetVLADPooling,
    load_netvlad,
)

CLUSTERS, DIM, PCS = 4, 8, 5


def _encoder() -> torch.nn.Sequential:
    return torch.nn.Sequential(torch.nn.Conv2d(3, DIM, 3, padding=1))


def _model(num_pcs: int | None = PCS, seed: int = 1) -> NetVLADModel:
    model = NetVLADModel(CLUSTERS, num_pcs, encoder=_encoder(), encoder_dim=DIM)
    randomise(model, seed)
    with torch.no_grad():
        model.pool.conv.weight.mul_(5.0)  # a sharp assignment, as trained models have
    return model


def _save(path, model: NetVLADModel, **extra) -> None:
    torch.save({"epoch": 7, "state_dict": model.state_dict(), **extra}, path)


def netvlad_reference(x: np.ndarray, conv: np.ndarray, centroids: np.ndarray) -> np.ndarray:
    """NetVLAD of one ``[D, h, w]`` map: per-position L2 normalisation, soft-assignment
    ``softmax_k(conv x)``, ``V[k] = sum_p a_kp (x_p - c_k)``, intra- then global L2."""
    points = x.reshape(x.shape[0], -1)
    points = points / np.linalg.norm(points, axis=0, keepdims=True)
    logits = conv @ points
    assign = np.exp(logits - logits.max(axis=0))
    assign = assign / assign.sum(axis=0)
    vlad = np.zeros_like(centroids)
    for k in range(centroids.shape[0]):
        for p in range(points.shape[1]):
            vlad[k] += assign[k, p] * (points[:, p] - centroids[k])
    vlad = vlad / np.linalg.norm(vlad, axis=1, keepdims=True)
    flat = vlad.reshape(-1)
    return flat / np.linalg.norm(flat)


def _expected(model: NetVLADModel, images: torch.Tensor, whiten: bool) -> np.ndarray:
    with torch.no_grad():
        maps = model.encoder.double()(images.double()).numpy()
    model.float()
    state = {k: v.double().numpy() for k, v in model.state_dict().items()}
    rows = []
    for x in maps:
        v = netvlad_reference(x, state["pool.conv.weight"][:, :, 0, 0], state["pool.centroids"])
        if whiten:
            v = state["WPCA.0.weight"][:, :, 0, 0] @ v + state["WPCA.0.bias"]
            v = v / np.linalg.norm(v)
        rows.append(v)
    return np.stack(rows)


def _images(seed: int = 0) -> torch.Tensor:
    return torch.randn(2, 3, 6, 7, generator=torch.Generator().manual_seed(seed))


def test_pooling_matches_float64_formula():
    pool = randomise(NetVLADPooling(CLUSTERS, DIM), seed=2)
    x = torch.randn(3, DIM, 4, 5, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    got = pool.double()(x).detach().numpy()
    state = {k: v.numpy() for k, v in pool.state_dict().items()}
    for b in range(3):
        expected = netvlad_reference(
            x[b].numpy(), state["conv.weight"][:, :, 0, 0], state["centroids"]
        )
        np.testing.assert_allclose(got[b], expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    ("variant", "whiten"),
    [
        ("patchnetvlad-pitts30k-4096", True),
        ("patchnetvlad-pitts30k-32768", False),
        ("nanne-pitts30k", False),
    ],
)
def test_loaded_checkpoint_matches_float64_reference(tmp_path, variant, whiten):
    source = _model(PCS if variant.startswith("patch") else None)
    path = tmp_path / VARIANTS[variant].published.file
    # Nanne's training script stores numpy scalars beside the weights.
    _save(path, source, best_score=np.float64(0.84), recalls={1: np.float64(0.8)})
    model = load_netvlad(str(path), variant, encoder=_encoder())
    images = _images()
    with torch.no_grad():
        got = model(images).numpy()
    assert got.shape == (2, PCS if whiten else CLUSTERS * DIM)
    np.testing.assert_allclose(got, _expected(source, images, whiten), rtol=0, atol=1e-6)


def test_data_parallel_keys_load(tmp_path):
    source = _model(None)
    state = {k.replace("encoder.", "encoder.module."): v for k, v in source.state_dict().items()}
    torch.save({"state_dict": state}, tmp_path / "checkpoint.pth.tar")
    model = load_netvlad(str(tmp_path / "checkpoint.pth.tar"), "nanne-pitts30k", encoder=_encoder())
    with torch.no_grad():
        np.testing.assert_array_equal(model(_images()).numpy(), source(_images()).numpy())


def test_published_sizes():
    assert DEFAULT_VARIANT == "patchnetvlad-pitts30k-4096"
    assert {name: v.dim for name, v in VARIANTS.items()} == {
        "patchnetvlad-pitts30k-4096": 4096,
        "patchnetvlad-pitts30k-32768": 32768,
        "patchnetvlad-pitts30k-512": 512,
        "patchnetvlad-pitts30k-128": 128,
        "nanne-pitts30k": 32768,
    }
    model = NetVLADModel(num_pcs=None)
    shapes = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    assert shapes["pool.centroids"] == (64, 512)
    assert shapes["pool.conv.weight"] == (64, 512, 1, 1)
    assert "pool.conv.bias" not in shapes
    assert shapes["encoder.28.weight"] == (512, 512, 3, 3)
    assert max(int(k.split(".")[1]) for k in shapes if k.startswith("encoder.")) == 28
    assert model.dim == 32768 and model.input_size == (480, 640)
    with torch.no_grad():
        assert model.feature_map(torch.zeros(1, 3, 48, 64)).shape == (1, 512, 3, 4)


def test_missing_file_names_variant_file_and_url(tmp_path):
    path = tmp_path / "absent.pth.tar"
    with pytest.raises(CheckpointError) as error:
        load_netvlad(str(path))
    message = str(error.value)
    assert DEFAULT_VARIANT in message and str(path) in message
    assert VARIANTS[DEFAULT_VARIANT].published.url in message


def test_unknown_variant_is_refused():
    with pytest.raises(ValueError, match="pitts250k"):
        load_netvlad("x", "pitts250k")


def test_unwhitened_checkpoint_for_whitened_variant_names_wpca(tmp_path):
    _save(tmp_path / "c.pth.tar", _model(None))
    with pytest.raises(CheckpointError, match=r"WPCA\.0\.weight"):
        load_netvlad(str(tmp_path / "c.pth.tar"), "patchnetvlad-pitts30k-4096", encoder=_encoder())


def test_mismatched_keys_are_named(tmp_path):
    state = _model().state_dict()
    del state["encoder.0.bias"]
    torch.save({"state_dict": state}, tmp_path / "c.pth.tar")
    with pytest.raises(CheckpointError, match=r"encoder\.0\.bias"):
        load_netvlad(str(tmp_path / "c.pth.tar"), encoder=_encoder())
    torch.save({"state_dict": {"encoder.0.weight": torch.zeros(1)}}, tmp_path / "d.pth.tar")
    with pytest.raises(CheckpointError, match=r"pool\.centroids"):
        load_netvlad(str(tmp_path / "d.pth.tar"), encoder=_encoder())


def test_published_model_refuses_other_cluster_count(tmp_path):
    state = NetVLADModel(num_pcs=None).state_dict()
    state["pool.centroids"] = torch.zeros(32, 512)
    state["pool.conv.weight"] = torch.zeros(32, 512, 1, 1)
    torch.save({"state_dict": state}, tmp_path / "c.pth.tar")
    with pytest.raises(CheckpointError, match=r"pool\.centroids.*\(32, 512\)"):
        load_netvlad(str(tmp_path / "c.pth.tar"), "nanne-pitts30k")
