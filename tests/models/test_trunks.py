"""The plain-torch ResNet trunk (vprflow.models.trunks.resnet): torchvision's exact
state-dict layout (key list and shapes written down from torchvision 0.28 once, as
hashes and parameter counts), the maps of layer1-4 against a float64 ResNet written
from the state dict's names (stride on the bottleneck's 3x3), and the loader's errors.
"""

from __future__ import annotations

import hashlib

import pytest
import torch
from torch.nn import functional as F

from vprflow.models.checkpoints import CheckpointError
from vprflow.models.trunks.resnet import (
    LAYERS,
    RESNET_DEPTHS,
    TORCHVISION_RESNET_URLS,
    ResNet,
    load_resnet,
    resnet_channels,
)

# depth -> (state-dict entries, parameters, sha256 of "key shape" lines in order), from
# torchvision.models.resnet<depth>().state_dict() (torchvision 0.28). The parameter
# counts are also those of torchvision's documentation (25.6M for ResNet-50).
TORCHVISION_LAYOUT = {
    18: (122, 11689512, "84fb10d9c6905a1cbb020b284537dc97c4f4ec55fb2a780a41152a23a2dd0e9d"),
    34: (218, 21797672, "28f9096d5130749948981c6900083e57b19456b8b835829b8bdfe415bddc3f32"),
    50: (320, 25557032, "d7e4f8bb0a5363446a59c81c3887ccf66900a11651a0ae2dec96d1bb1eb6ea81"),
    101: (626, 44549160, "02c0f34f4842751f30e27e18a544ca36a8b33358f344c3c3165fd269ce97cd94"),
    152: (932, 60192808, "685c66205bc823aa68246b01dc5273074689b1c11ed0503f961f21c380191d3b"),
}


def _layout(state: dict) -> tuple[int, int, str]:
    text = "\n".join(f"{k} {tuple(v.shape)}" for k, v in state.items())
    parameters = sum(
        v.numel()
        for k, v in state.items()
        if not k.endswith(("running_mean", "running_var", "num_batches_tracked"))
    )
    return len(state), parameters, hashlib.sha256(text.encode()).hexdigest()


def _randomise(model: torch.nn.Module, seed: int) -> torch.nn.Module:
    """He-scaled convolutions; BatchNorm weights, biases and statistics perturbed so that
    no BatchNorm is the identity (a swapped mean / variance would show)."""
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, tensor in model.state_dict().items():
            noise = torch.randn(tensor.shape, generator=generator, dtype=torch.float64)
            if name.endswith("num_batches_tracked"):
                continue
            if name.endswith("running_var"):
                tensor.copy_(0.5 + noise.abs())
            elif name.endswith(("running_mean", "bias")):
                tensor.copy_(0.1 * noise)
            elif tensor.ndim == 1:  # BatchNorm weight
                tensor.copy_(0.7 + 0.1 * noise)
            else:
                tensor.copy_(noise * (2.0 / tensor[0].numel()) ** 0.5)
    return model.eval()


def _bn(x, state, name):
    shape = (1, -1, 1, 1)
    mean, var = state[f"{name}.running_mean"].view(shape), state[f"{name}.running_var"].view(shape)
    weight, bias = state[f"{name}.weight"].view(shape), state[f"{name}.bias"].view(shape)
    return (x - mean) / torch.sqrt(var + 1e-5) * weight + bias


def reference_maps(state: dict, images: torch.Tensor, depth: int) -> dict[str, torch.Tensor]:
    """Float64 ResNet maps of layer1-4 from torchvision-named weights (He et al. with
    torchvision's "v1.5" stride on the 3x3 of a bottleneck)."""
    state = {k: v.double() for k, v in state.items()}
    x = F.relu(
        _bn(F.conv2d(images.double(), state["conv1.weight"], stride=2, padding=3), state, "bn1")
    )
    x = F.max_pool2d(x, 3, stride=2, padding=1)
    kind, blocks = RESNET_DEPTHS[depth]
    maps = {}
    for stage, count in enumerate(blocks):
        for index in range(count):
            name = f"layer{stage + 1}.{index}"
            stride = 2 if stage > 0 and index == 0 else 1
            if f"{name}.downsample.0.weight" in state:
                shortcut = _bn(
                    F.conv2d(x, state[f"{name}.downsample.0.weight"], stride=stride),
                    state,
                    f"{name}.downsample.1",
                )
            else:
                shortcut = x
            if kind == "basic":
                out = F.relu(
                    _bn(
                        F.conv2d(x, state[f"{name}.conv1.weight"], stride=stride, padding=1),
                        state,
                        f"{name}.bn1",
                    )
                )
                out = _bn(
                    F.conv2d(out, state[f"{name}.conv2.weight"], padding=1), state, f"{name}.bn2"
                )
            else:
                out = F.relu(_bn(F.conv2d(x, state[f"{name}.conv1.weight"]), state, f"{name}.bn1"))
                out = F.relu(
                    _bn(
                        F.conv2d(out, state[f"{name}.conv2.weight"], stride=stride, padding=1),
                        state,
                        f"{name}.bn2",
                    )
                )
                out = _bn(F.conv2d(out, state[f"{name}.conv3.weight"]), state, f"{name}.bn3")
            x = F.relu(out + shortcut)
        maps[f"layer{stage + 1}"] = x
    return maps


@pytest.mark.parametrize("depth", sorted(TORCHVISION_LAYOUT))
def test_state_dict_is_torchvisions(depth):
    state = ResNet(depth, classifier=True).state_dict()
    assert _layout(state) == TORCHVISION_LAYOUT[depth]


def test_resnet50_landmark_keys():
    state = ResNet(50, classifier=True).state_dict()
    expected = {
        "conv1.weight": (64, 3, 7, 7),
        "bn1.running_var": (64,),
        "layer1.0.downsample.0.weight": (256, 64, 1, 1),
        "layer2.0.conv2.weight": (128, 128, 3, 3),
        "layer3.5.bn3.num_batches_tracked": (),
        "layer4.2.conv3.weight": (2048, 512, 1, 1),
        "fc.weight": (1000, 2048),
    }
    assert {k: tuple(state[k].shape) for k in expected} == expected
    assert "layer1.1.downsample.0.weight" not in state


def test_truncated_trunk_has_no_later_keys():
    keys = ResNet(50, "layer3").state_dict().keys()
    assert not any(k.startswith(("layer4.", "fc.")) for k in keys)
    assert "layer3.5.conv3.weight" in keys


@pytest.mark.parametrize("depth", [18, 50])
def test_maps_equal_float64_reference(depth):
    trunk = _randomise(ResNet(depth, classifier=True), seed=depth)
    images = torch.randn(2, 3, 70, 93, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        maps = trunk.feature_maps(images, LAYERS)
    expected = reference_maps(trunk.state_dict(), images, depth)
    for layer in LAYERS:
        # ceil(H / stride) positions (floor of each padded convolution / pool)
        stride = {"layer1": 4, "layer2": 8, "layer3": 16, "layer4": 32}[layer]
        assert maps[layer].shape == (
            2,
            resnet_channels(depth, layer),
            -(-70 // stride),
            -(-93 // stride),
        )
        assert expected[layer].abs().max() > 0.1  # not collapsed
        torch.testing.assert_close(maps[layer].double(), expected[layer], rtol=1e-4, atol=1e-4)


def test_channels():
    assert [resnet_channels(50, layer) for layer in LAYERS] == [256, 512, 1024, 2048]
    assert [resnet_channels(18, layer) for layer in LAYERS] == [64, 128, 256, 512]
    with pytest.raises(ValueError, match="layer5"):
        resnet_channels(50, "layer5")
    with pytest.raises(ValueError, match="depth 42"):
        ResNet(42)


def test_feature_map_and_forward():
    trunk = _randomise(ResNet(18, "layer3"), seed=3)
    images = torch.randn(1, 3, 64, 64)
    with torch.no_grad():
        assert torch.equal(trunk(images), trunk.feature_map(images, "layer3"))
        assert trunk.feature_map(images, "layer1").shape == (1, 64, 16, 16)
    with pytest.raises(ValueError, match="'layer4' is not part of this trunk"):
        trunk.feature_map(images, "layer4")
    with pytest.raises(ValueError, match="whole trunk"):
        ResNet(18, "layer3", classifier=True)


def test_classifier_logits():
    trunk = _randomise(ResNet(18, classifier=True), seed=4)
    images = torch.randn(2, 3, 64, 64)
    with torch.no_grad():
        logits = trunk(images)
        pooled = trunk.feature_map(images).double().mean(dim=(2, 3))
    expected = pooled @ trunk.fc.weight.double().T + trunk.fc.bias.double()
    torch.testing.assert_close(logits.double(), expected, rtol=1e-5, atol=1e-5)


def test_load_resnet_torchvision_checkpoint(tmp_path):
    source = _randomise(ResNet(50, classifier=True), seed=5)
    path = tmp_path / "resnet50-0676ba61.pth"
    torch.save(source.state_dict(), path)
    images = torch.randn(1, 3, 64, 64)
    trunk = load_resnet(str(path), 50, "layer3")  # layer4 and fc are ignored
    assert not trunk.training
    with torch.no_grad():
        torch.testing.assert_close(
            trunk(images), source.feature_map(images, "layer3"), rtol=0, atol=0
        )
    full = load_resnet(str(path), 50, classifier=True)
    with torch.no_grad():
        torch.testing.assert_close(full(images), source(images), rtol=0, atol=0)


def test_load_resnet_errors(tmp_path):
    missing = tmp_path / "absent.pth"
    with pytest.raises(CheckpointError, match="absent.pth") as error:
        load_resnet(str(missing), 50)
    assert TORCHVISION_RESNET_URLS[50] in str(error.value)

    small = tmp_path / "resnet18.pth"
    torch.save(ResNet(18, classifier=True).state_dict(), small)
    with pytest.raises(CheckpointError, match="resnet18.pth.*missing keys") as error:
        load_resnet(str(small), 50)
    assert "ResNet-50" in str(error.value)

    state = ResNet(50).state_dict()
    state["layer2.0.conv2.weight"] = torch.zeros(128, 128, 1, 1)
    wrong = tmp_path / "wrong.pth"
    torch.save(state, wrong)
    with pytest.raises(
        CheckpointError, match=r"'layer2.0.conv2.weight' has shape \(128, 128, 1, 1\)"
    ):
        load_resnet(str(wrong), 50)

    torch.save(["not", "a", "state dict"], tmp_path / "list.pth")
    with pytest.raises(CheckpointError, match="list.pth.*not a state dict"):
        load_resnet(str(tmp_path / "list.pth"), 50)
