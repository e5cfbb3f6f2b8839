"""VGG16 trunk (vprflow.models.trunks.vgg): torchvision's key layout, conv5_3 before its
ReLU, the forward against float64 convolutions, and the loader's errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.nn import functional as F
from trained_references import randomise

from vprflow.models.checkpoints import CheckpointError
from vprflow.models.trunks.vgg import (
    TORCHVISION_VGG16_URL,
    VGG16Trunk,
    load_vgg16_trunk,
    vgg16_features,
)

# torchvision's vgg16().features: index of each convolution, its (out, in) channels.
CONVS = {
    0: (64, 3),
    2: (64, 64),
    5: (128, 64),
    7: (128, 128),
    10: (256, 128),
    12: (256, 256),
    14: (256, 256),
    17: (512, 256),
    19: (512, 512),
    21: (512, 512),
    24: (512, 512),
    26: (512, 512),
    28: (512, 512),
}
POOLS = (4, 9, 16, 23, 30)


def test_layout_is_torchvisions():
    features = vgg16_features("pool5")
    shapes = {k: tuple(v.shape) for k, v in features.state_dict().items()}
    expected = {}
    for index, (out, inp) in CONVS.items():
        expected[f"{index}.weight"] = (out, inp, 3, 3)
        expected[f"{index}.bias"] = (out,)
    assert shapes == expected
    assert [i for i, m in enumerate(features) if isinstance(m, torch.nn.MaxPool2d)] == list(POOLS)
    assert len(vgg16_features("conv5_3")) == 29
    assert isinstance(vgg16_features("conv5_3")[28], torch.nn.Conv2d)
    assert len(vgg16_features("relu5_3")) == 30


def test_unknown_end_is_refused():
    with pytest.raises(ValueError, match="conv5_4"):
        vgg16_features("conv5_4")


def _reference(state: dict[str, torch.Tensor], images: torch.Tensor, last: int) -> torch.Tensor:
    """Convolutions 3x3 / pad 1 with ReLU between, max-pools at POOLS, in float64,
    stopping after module ``last`` of torchvision's ``features``."""
    x = images.double()
    for index in range(last + 1):
        if index in CONVS:
            x = F.conv2d(
                x,
                state[f"features.{index}.weight"].double(),
                state[f"features.{index}.bias"].double(),
                padding=1,
            )
        elif index in POOLS:
            x = F.max_pool2d(x, 2)
        else:
            x = F.relu(x)
    return x


@pytest.mark.parametrize(("end", "last", "stride"), [("conv5_3", 28, 16), ("pool5", 30, 32)])
def test_forward_matches_float64_reference(end, last, stride):
    trunk = randomise(VGG16Trunk(end), seed=1)
    images = torch.randn(2, 3, 64, 96, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        got = trunk(images)
    expected = _reference(trunk.state_dict(), images, last)
    assert got.shape == (2, 512, 64 // stride, 96 // stride)
    scale = float(expected.abs().max())
    np.testing.assert_allclose(got.numpy(), expected.numpy(), rtol=0, atol=1e-5 * scale)
    if end == "conv5_3":  # no ReLU after conv5_3: NetVLAD sees negative values
        assert float(got.min()) < 0


def test_loader_reads_torchvision_state_dict(tmp_path):
    source = randomise(VGG16Trunk("pool5"), seed=3)
    state = {f"features.{k}": v for k, v in source.features.state_dict().items()}
    state["classifier.0.weight"] = torch.zeros(4, 7)  # the classifier is not the trunk's
    path = tmp_path / "vgg16-397923af.pth"
    torch.save(state, path)
    trunk = load_vgg16_trunk(str(path))
    images = torch.randn(1, 3, 32, 32, generator=torch.Generator().manual_seed(4))
    with torch.no_grad():
        np.testing.assert_array_equal(trunk(images).numpy(), source.features[:29](images).numpy())


def test_loader_errors_name_key_and_url(tmp_path):
    with pytest.raises(CheckpointError, match=TORCHVISION_VGG16_URL.replace(".", r"\.")):
        load_vgg16_trunk(str(tmp_path / "absent.pth"))
    state = {f"features.{k}": v for k, v in VGG16Trunk().features.state_dict().items()}
    del state["features.26.bias"]
    torch.save(state, tmp_path / "partial.pth")
    with pytest.raises(CheckpointError, match="features.26.bias"):
        load_vgg16_trunk(str(tmp_path / "partial.pth"))
    state["features.26.bias"] = torch.zeros(3)
    torch.save(state, tmp_path / "shape.pth")
    with pytest.raises(CheckpointError, match=r"features\.26\.bias.*\(3,\)"):
        load_vgg16_trunk(str(tmp_path / "shape.pth"))
