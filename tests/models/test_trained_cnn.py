"""The ResNet-based trained VPR models (vprflow.models.trained: cosplace, mixvpr, convap,
boq) against float64 formulas written here from the papers and the original
repositories' equations, loaded through their real loaders from random weights saved in
each published checkpoint's key layout (named explicitly below), and the loaders' errors.

The trunks' maps are checked in test_trunks.py; here each head is checked on the map the
model's own ``feature_map`` returns, and the map itself against a torchvision-named
:class:`ResNet` given the same weights (so the checkpoint's ``backbone.<i>`` /
``backbone.net.<i>`` / ``backbone.model.<name>`` are mapped onto the right layers).
"""

from __future__ import annotations

import re

import pytest
import torch
from torch.nn import functional as F

from vprflow.models.checkpoints import CheckpointError
from vprflow.models.kinds import trained_model
from vprflow.models.trained.boq import BoQAggregator, BoQResNet, load_boq_resnet50
from vprflow.models.trained.convap import ConvAP, ConvAPAggregator, load_convap
from vprflow.models.trained.cosplace import (
    GeM,
    GeoLocalizationNet,
    load_cosplace,
    load_eigenplaces,
)
from vprflow.models.trained.mixvpr import MixVPR, load_mixvpr
from vprflow.models.trunks.resnet import STAGES, ResNet

IMAGENET = ((0.485, 0.456, 0.406), (0.229, 0.224, 0.225))
MIXVPR_URL, CONVAP_URL, BOQ_RESNET50_URL = (
    trained_model(kind).published().url for kind in ("mixvpr", "convap", "boq_resnet50")
)


def _randomise(model: torch.nn.Module, seed: int) -> torch.nn.Module:
    """Every float tensor of the state dict re-drawn: He-scaled weights, norms near 1,
    positive variances, GeM's p near 3, O(1) queries."""
    generator = torch.Generator().manual_seed(seed)
    norms = {
        name
        for name, module in model.named_modules()
        if isinstance(module, (torch.nn.BatchNorm2d, torch.nn.LayerNorm))
    }
    with torch.no_grad():
        for key, tensor in model.state_dict().items():
            if not tensor.is_floating_point():
                continue
            owner, _, leaf = key.rpartition(".")
            noise = torch.randn(tensor.shape, generator=generator, dtype=torch.float64)
            if leaf == "running_var":
                value = 0.5 + noise.abs()
            elif leaf == "p":
                value = 3.0 + 0.3 * noise
            elif owner in norms and leaf == "weight":
                value = 0.8 + 0.1 * noise
            elif tensor.ndim == 1 or leaf == "running_mean":
                value = 0.1 * noise
            elif leaf == "queries":
                value = noise
            else:
                value = noise * (2.0 / tensor[0].numel()) ** 0.5
            tensor.copy_(value)
    return model.eval()


def _images(batch: int = 2, height: int = 64, width: int = 64, seed: int = 0) -> torch.Tensor:
    return torch.randn(batch, 3, height, width, generator=torch.Generator().manual_seed(seed))


def _double(state: dict, prefix: str) -> dict[str, torch.Tensor]:
    return {k[len(prefix) :]: v.double() for k, v in state.items() if k.startswith(prefix)}


def _stripped(state: dict, prefix: str) -> dict[str, torch.Tensor]:
    return {k[len(prefix) :]: v for k, v in state.items() if k.startswith(prefix)}


def _torchvision_named(state: dict, pattern: str) -> dict[str, torch.Tensor]:
    """``backbone.<i>.rest`` (``pattern`` matching the index) -> torchvision's name."""
    renamed = {}
    for key, value in state.items():
        match = re.match(pattern, key)
        if match:
            renamed[f"{STAGES[int(match.group(1))]}.{match.group(2)}"] = value
    return renamed


def _assert_same_trunk(state: dict, pattern: str, end: str, model, images: torch.Tensor):
    trunk = ResNet(50, end)
    trunk.load_state_dict(_torchvision_named(state, pattern))
    trunk.eval()
    with torch.no_grad():
        torch.testing.assert_close(model.feature_map(images, end), trunk(images), rtol=0, atol=0)


# --- CosPlace / EigenPlaces ----------------------------------------------------------


def gem_reference(x: torch.Tensor, p: float, eps: float = 1e-6) -> torch.Tensor:
    """GeM (Radenović et al.): ``(mean over positions of max(x, eps)^p)^(1/p)``."""
    return x.double().clamp(min=eps).pow(p).mean(dim=(2, 3)).pow(1.0 / p)


def cosplace_reference(state: dict, feature_map: torch.Tensor) -> torch.Tensor:
    """CosPlace's head: per-position L2, GeM, fully connected, L2."""
    x = F.normalize(feature_map.double(), dim=1)
    pooled = gem_reference(x, float(state["aggregation.1.p"]))
    out = pooled @ state["aggregation.3.weight"].double().T + state["aggregation.3.bias"].double()
    return F.normalize(out, dim=1)


def test_gem_equals_formula():
    gem = GeM(p=3.0)
    with torch.no_grad():
        gem.p.fill_(2.5)
    x = torch.randn(2, 5, 3, 4, generator=torch.Generator().manual_seed(1))
    out = gem(x)
    assert out.shape == (2, 5, 1, 1)
    torch.testing.assert_close(
        out[:, :, 0, 0].double(), gem_reference(x, 2.5), rtol=1e-5, atol=1e-6
    )
    # negatives are clamped to eps before the power, not taken as |x|
    with torch.no_grad():
        clamped = float(gem(-torch.ones(1, 1, 2, 2)))
    assert clamped == pytest.approx(1e-6, rel=1e-3)


def test_cosplace_checkpoint_layout_and_formula(tmp_path):
    source = _randomise(GeoLocalizationNet("ResNet50", 2048), seed=1)
    state = source.state_dict()
    # The published layout: the ResNet children as an nn.Sequential, then the head.
    expected_keys = {
        "backbone.0.weight": (64, 3, 7, 7),
        "backbone.1.running_mean": (64,),
        "backbone.4.0.downsample.0.weight": (256, 64, 1, 1),
        "backbone.7.2.conv3.weight": (2048, 512, 1, 1),
        "aggregation.1.p": (1,),
        "aggregation.3.weight": (2048, 2048),
        "aggregation.3.bias": (2048,),
    }
    assert {k: tuple(state[k].shape) for k in expected_keys} == expected_keys
    assert not any(re.match(r"backbone\.[238]\.", k) for k in state)  # relu, maxpool: no keys
    path = tmp_path / "ResNet50_2048_cosplace.pth"
    torch.save(state, path)

    model = load_cosplace(str(path))
    assert (model.dim, model.input_size) == (2048, None)
    assert (model.mean, model.std) == IMAGENET
    images = _images()
    with torch.no_grad():
        descriptors = model(images)
        feature_map = model.feature_map(images)
    assert feature_map.shape == (2, 2048, 2, 2)
    torch.testing.assert_close(
        descriptors.double(), cosplace_reference(state, feature_map), rtol=1e-4, atol=1e-5
    )
    torch.testing.assert_close(descriptors.norm(dim=1), torch.ones(2))
    _assert_same_trunk(state, r"backbone\.(\d)\.(.+)", "layer4", model, images)
    with torch.no_grad():
        assert model.feature_map(images, "layer3").shape == (2, 1024, 4, 4)


def test_eigenplaces_resnet18(tmp_path):
    source = _randomise(GeoLocalizationNet("ResNet18", 512), seed=2)
    path = tmp_path / "ResNet18_512_eigenplaces.pth"
    torch.save(source.state_dict(), path)
    model = load_eigenplaces(str(path), "ResNet18", 512)
    images = _images(height=96, width=64)
    with torch.no_grad():
        feature_map = model.feature_map(images)
        descriptors = model(images)
    assert feature_map.shape == (2, 512, 3, 2)
    torch.testing.assert_close(
        descriptors.double(),
        cosplace_reference(source.state_dict(), feature_map),
        rtol=1e-4,
        atol=1e-5,
    )


def test_cosplace_loader_errors(tmp_path):
    with pytest.raises(
        ValueError, match="EigenPlaces publishes no ResNet152 model of dimension 2048"
    ):
        load_eigenplaces(str(tmp_path / "x.pth"), "ResNet152", 2048)
    with pytest.raises(ValueError, match="CosPlace publishes no ResNet50 model of dimension 100"):
        load_cosplace(str(tmp_path / "x.pth"), "ResNet50", 100)

    url = "https://github.com/gmberton/CosPlace/releases/download/v1.0/ResNet50_2048_cosplace.pth"
    with pytest.raises(CheckpointError, match="CosPlace ResNet50-2048.*absent.pth") as error:
        load_cosplace(str(tmp_path / "absent.pth"))
    assert url in str(error.value)

    smaller = tmp_path / "ResNet50_512_cosplace.pth"
    torch.save(GeoLocalizationNet("ResNet50", 512).state_dict(), smaller)
    with pytest.raises(
        CheckpointError, match=r"'aggregation.3.weight' has shape \(512, 2048\)"
    ) as error:
        load_cosplace(str(smaller), "ResNet50", 2048)
    assert url in str(error.value)

    # A torchvision-named trunk (e.g. a MixVPR-style file) is not CosPlace's layout.
    renamed = tmp_path / "renamed.pth"
    state = GeoLocalizationNet("ResNet18", 512).state_dict()
    torch.save({k.replace("backbone.0.", "backbone.conv1."): v for k, v in state.items()}, renamed)
    with pytest.raises(
        CheckpointError, match=r"missing keys \['backbone.0.weight'\].*backbone.conv1.weight"
    ):
        load_eigenplaces(str(renamed), "ResNet18", 512)


# --- MixVPR ------------------------------------------------------------------------


def mixvpr_reference(state: dict, feature_map: torch.Tensor) -> torch.Tensor:
    """MixVPR's aggregation: Feature-Mixer residual MLPs over the flattened positions of
    each channel, projections over channels then positions, channel-major flatten, L2."""
    w = _double(state, "aggregator.")
    x = feature_map.double().flatten(2)  # [B, C, n]
    depth = len({k.split(".")[1] for k in w if k.startswith("mix.")})
    for i in range(depth):
        p = f"mix.{i}.mix."
        h = F.layer_norm(x, x.shape[-1:], w[p + "0.weight"], w[p + "0.bias"], eps=1e-5)
        h = torch.relu(h @ w[p + "1.weight"].T + w[p + "1.bias"])
        x = x + h @ w[p + "3.weight"].T + w[p + "3.bias"]
    x = torch.einsum("bcn,oc->bon", x, w["channel_proj.weight"]) + w["channel_proj.bias"][:, None]
    x = torch.einsum("bon,rn->bor", x, w["row_proj.weight"]) + w["row_proj.bias"]
    return F.normalize(x.flatten(1), dim=1)


def test_mixvpr_published_configuration():
    model = MixVPR()
    state = model.state_dict()
    assert (model.dim, model.input_size, (model.mean, model.std)) == (4096, (320, 320), IMAGENET)
    assert tuple(state["aggregator.mix.3.mix.1.weight"].shape) == (400, 400)
    assert tuple(state["aggregator.channel_proj.weight"].shape) == (1024, 1024)
    assert tuple(state["aggregator.row_proj.weight"].shape) == (4, 400)
    assert "backbone.model.layer3.5.conv3.weight" in state
    assert not any(k.startswith(("backbone.model.layer4.", "backbone.model.fc.")) for k in state)


def test_mixvpr_lightning_checkpoint_and_formula(tmp_path):
    # 64 x 64 input -> a 4 x 4 layer3 map, so 16 positions; a smaller head than published.
    source = _randomise(MixVPR(positions=16, out_channels=8, mix_depth=2, out_rows=3), seed=3)
    state = source.state_dict()
    assert "backbone.model.conv1.weight" in state and "aggregator.mix.1.mix.3.bias" in state
    path = tmp_path / "mixvpr.ckpt"
    torch.save({"epoch": 3, "hyper_parameters": {"agg_arch": "MixVPR"}, "state_dict": state}, path)

    model = load_mixvpr(str(path))
    assert (model.dim, model.input_size) == (24, (64, 64))
    assert len(model.aggregator.mix) == 2
    images = _images()
    with torch.no_grad():
        feature_map = model.feature_map(images)
        descriptors = model(images)
    assert feature_map.shape == (2, 1024, 4, 4)
    torch.testing.assert_close(
        descriptors.double(), mixvpr_reference(state, feature_map), rtol=1e-4, atol=1e-5
    )
    trunk = ResNet(50, "layer3")
    trunk.load_state_dict(_stripped(state, "backbone.model."))
    with torch.no_grad():
        torch.testing.assert_close(feature_map, trunk.eval()(images), rtol=0, atol=0)
    with pytest.raises(ValueError, match="16 positions; got 36"):
        model(_images(height=96, width=96))


def test_mixvpr_plain_state_dict_and_errors(tmp_path):
    source = _randomise(MixVPR(positions=16, out_channels=4, mix_depth=1, out_rows=2), seed=4)
    plain = tmp_path / "plain.ckpt"
    torch.save(source.state_dict(), plain)  # the README's torch.load + load_state_dict
    assert load_mixvpr(str(plain)).dim == 8

    with pytest.raises(CheckpointError, match="MixVPR.*absent.ckpt") as error:
        load_mixvpr(str(tmp_path / "absent.ckpt"))
    assert MIXVPR_URL in str(error.value)

    cosplace = tmp_path / "cosplace.pth"
    torch.save(GeoLocalizationNet("ResNet18", 32).state_dict(), cosplace)
    with pytest.raises(CheckpointError, match="cosplace.pth.*'aggregator.row_proj.weight'"):
        load_mixvpr(str(cosplace))

    state = source.state_dict()
    state["backbone.model.layer4.0.conv1.weight"] = torch.zeros(512, 1024, 1, 1)
    extra = tmp_path / "extra.ckpt"
    torch.save(state, extra)
    with pytest.raises(
        CheckpointError, match=r"unexpected keys \['backbone.model.layer4.0.conv1.weight'\]"
    ):
        load_mixvpr(str(extra))


# --- Conv-AP -----------------------------------------------------------------------


def convap_reference(state: dict, feature_map: torch.Tensor) -> torch.Tensor:
    """Conv-AP: 1x1 convolution, mean over each of 2 x 2 cells (cell i spans rows
    floor(i h / 2) .. ceil((i + 1) h / 2), likewise columns), channel-major flatten, L2."""
    w = _double(state, "aggregator.channel_pool.")
    x = torch.einsum("bchw,oc->bohw", feature_map.double(), w["weight"][:, :, 0, 0])
    x = x + w["bias"][:, None, None]
    h, wd = x.shape[2:]
    cells = []
    for i in range(2):
        for j in range(2):
            rows = slice(i * h // 2, -(-(i + 1) * h // 2))
            cols = slice(j * wd // 2, -(-(j + 1) * wd // 2))
            cells.append(x[:, :, rows, cols].mean(dim=(2, 3)))
    return F.normalize(torch.stack(cells, dim=2).flatten(1), dim=1)


@pytest.mark.parametrize("size", [(128, 128), (96, 160)])  # 4 x 4 and 3 x 5 maps
def test_convap_checkpoint_and_formula(tmp_path, size):
    source = _randomise(ConvAP(out_channels=16), seed=5)
    state = source.state_dict()
    assert tuple(state["aggregator.channel_pool.weight"].shape) == (16, 2048, 1, 1)
    assert "backbone.model.layer4.2.bn3.running_var" in state
    assert not any(k.startswith("backbone.model.fc.") for k in state)
    path = tmp_path / "convap.ckpt"
    torch.save({"state_dict": state}, path)

    model = load_convap(str(path))
    assert (model.dim, model.input_size) == (64, (320, 320))
    images = _images(height=size[0], width=size[1])
    with torch.no_grad():
        feature_map = model.feature_map(images)
        descriptors = model(images)
    torch.testing.assert_close(
        descriptors.double(), convap_reference(state, feature_map), rtol=1e-4, atol=1e-5
    )
    trunk = ResNet(50, "layer4")
    trunk.load_state_dict(_stripped(state, "backbone.model."))
    with torch.no_grad():
        torch.testing.assert_close(feature_map, trunk.eval()(images), rtol=0, atol=0)


def test_convap_published_sizes_and_errors(tmp_path):
    assert ConvAP().dim == 4096 and ConvAP(out_channels=2048).dim == 8192
    assert isinstance(ConvAP().aggregator, ConvAPAggregator)
    source = ConvAP(out_channels=16)
    path = tmp_path / "small.ckpt"
    torch.save(source.state_dict(), path)
    with pytest.raises(
        CheckpointError, match=r"small.ckpt.*\(16, 2048, 1, 1\), giving 64-d"
    ) as error:
        load_convap(str(path), 4096)
    assert "resnet50_ConvAP_1024_2x2.ckpt" in str(error.value) and CONVAP_URL in str(error.value)
    with pytest.raises(ValueError, match="no 100-d model"):
        load_convap(str(path), 100)
    state = source.state_dict()
    del state["backbone.model.bn1.running_mean"]
    torch.save(state, path)
    with pytest.raises(
        CheckpointError, match=r"missing keys \['backbone.model.bn1.running_mean'\]"
    ):
        load_convap(str(path))


# --- BoQ-ResNet50 ------------------------------------------------------------------


def _attention(w: dict, prefix: str, query: torch.Tensor, memory: torch.Tensor, heads: int):
    """torch's multi-head attention: in-projection, softmax(q k^T / sqrt(d)) v per head,
    out-projection."""
    wq, wk, wv = w[prefix + "in_proj_weight"].chunk(3)
    bq, bk, bv = w[prefix + "in_proj_bias"].chunk(3)
    batch, length, dim = query.shape

    def split(x):
        return x.reshape(batch, x.shape[1], heads, dim // heads).transpose(1, 2)

    q, k, v = split(query @ wq.T + bq), split(memory @ wk.T + bk), split(memory @ wv.T + bv)
    weights = torch.softmax(q @ k.transpose(-1, -2) / (dim // heads) ** 0.5, dim=-1)
    out = (weights @ v).transpose(1, 2).reshape(batch, length, dim)
    return out @ w[prefix + "out_proj.weight"].T + w[prefix + "out_proj.bias"]


def _norm(w, prefix, x):
    return F.layer_norm(x, x.shape[-1:], w[prefix + "weight"], w[prefix + "bias"], eps=1e-5)


def boq_reference(
    state: dict, feature_map: torch.Tensor, prefix: str = "aggregator."
) -> torch.Tensor:
    """Bag-of-Queries (Ali-bey et al. 2024): 3x3 projection, LayerNorm, per block a
    post-norm transformer encoder layer on the tokens and queries (self-attended, then
    cross-attending to the tokens); the blocks' outputs concatenated over queries, a
    linear map from queries to rows per channel, channel-major flatten, L2."""
    w = _double(state, prefix)
    dim = w["proj_c.weight"].shape[0]
    heads = dim // 64
    x = F.conv2d(feature_map.double(), w["proj_c.weight"], w["proj_c.bias"], padding=1)
    x = _norm(w, "norm_input.", x.flatten(2).transpose(1, 2))
    outputs = []
    blocks = len({k.split(".")[1] for k in w if k.startswith("boqs.")})
    for i in range(blocks):
        p = f"boqs.{i}."
        x = _norm(w, p + "encoder.norm1.", x + _attention(w, p + "encoder.self_attn.", x, x, heads))
        hidden = torch.relu(x @ w[p + "encoder.linear1.weight"].T + w[p + "encoder.linear1.bias"])
        x = _norm(
            w,
            p + "encoder.norm2.",
            x + hidden @ w[p + "encoder.linear2.weight"].T + w[p + "encoder.linear2.bias"],
        )
        q = w[p + "queries"].expand(x.shape[0], -1, -1)
        q = _norm(w, p + "norm_q.", q + _attention(w, p + "self_attn.", q, q, heads))
        outputs.append(_norm(w, p + "norm_out.", _attention(w, p + "cross_attn.", q, x, heads)))
    out = torch.cat(outputs, dim=1).transpose(1, 2) @ w["fc.weight"].T + w["fc.bias"]
    return F.normalize(out.flatten(1), dim=1)


def test_boq_aggregator_equals_formula():
    head = _randomise(
        BoQAggregator(8, proj_channels=128, num_queries=4, num_layers=2, row_dim=3), seed=6
    )
    x = torch.randn(2, 8, 5, 6, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        out = head(x)
    assert out.shape == (2, 384)
    state = {f"aggregator.{k}": v for k, v in head.state_dict().items()}
    torch.testing.assert_close(out.double(), boq_reference(state, x), rtol=1e-4, atol=1e-5)


def test_boq_published_configuration():
    model = BoQResNet()
    state = model.state_dict()
    assert (model.dim, model.input_size, (model.mean, model.std)) == (16384, (384, 384), IMAGENET)
    expected = {
        "backbone.net.0.weight": (64, 3, 7, 7),
        "backbone.net.6.5.conv3.weight": (1024, 256, 1, 1),
        "aggregator.proj_c.weight": (512, 1024, 3, 3),
        "aggregator.boqs.1.queries": (1, 64, 512),
        "aggregator.boqs.0.encoder.self_attn.in_proj_weight": (1536, 512),
        "aggregator.boqs.0.encoder.linear1.weight": (2048, 512),
        "aggregator.boqs.1.cross_attn.out_proj.weight": (512, 512),
        "aggregator.fc.weight": (32, 128),
    }
    assert {k: tuple(state[k].shape) for k in expected} == expected
    assert not any(k.startswith("backbone.net.7.") for k in state)
    assert model.aggregator.boqs[0].cross_attn.num_heads == 8


def test_boq_checkpoint_and_formula(tmp_path):
    small = {"proj_channels": 64, "num_queries": 3, "num_layers": 2, "row_dim": 2}
    source = _randomise(BoQResNet(**small), seed=7)
    state = source.state_dict()
    path = tmp_path / "resnet50_16384.pth"
    torch.save(state, path)
    model = load_boq_resnet50(str(path), **small)
    images = _images()
    with torch.no_grad():
        feature_map = model.feature_map(images)
        descriptors = model(images)
    assert feature_map.shape == (2, 1024, 4, 4) and descriptors.shape == (2, 128)
    torch.testing.assert_close(
        descriptors.double(), boq_reference(state, feature_map), rtol=1e-4, atol=1e-5
    )
    _assert_same_trunk(state, r"backbone\.net\.(\d)\.(.+)", "layer3", model, images)

    with pytest.raises(
        CheckpointError, match="BoQ-ResNet50.*resnet50_16384.pth.*has shape"
    ) as error:
        load_boq_resnet50(str(path))  # published head sizes: the small file does not fit
    assert BOQ_RESNET50_URL in str(error.value)
