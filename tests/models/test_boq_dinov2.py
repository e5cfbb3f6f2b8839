"""BoQ with DINOv2 (vprflow.models.trained.boq_dinov2): the shared BoQ head at its sizes
against a float64 composition of torch's ``MultiheadAttention`` /
``TransformerEncoderLayer`` (the modules the original is built from), the backbone
without its final norm against the float64 ViT, and
the loader on random weights saved in the ``dinov2_12288.pth`` layout
(``backbone.dino.<torch-hub DINOv2>``, ``aggregator.*``) with a tiny 2-block ViT."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn
from torch.nn import functional as F
from trained_references import prefixed, randomise, tiny_config, vit_reference

from vprflow.models.checkpoints import CheckpointError
from vprflow.models.kinds import trained_model
from vprflow.models.trained.boq import BoQAggregator
from vprflow.models.trained.boq_dinov2 import PROJ_CHANNELS, BoQDinoV2, load_boq_dinov2
from vprflow.models.trunks.dinov2 import dinov2_hub_state_dict

BOQ_DINOV2_URL = trained_model("boq_dinov2").published().url

# proj_channels 128 -> 2 heads (BoQ uses proj_channels // 64).
SIZES = {"proj_channels": 128, "num_queries": 4, "num_layers": 2, "row_dim": 3}


def _generator(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def boq_reference(aggregator: BoQAggregator, x: torch.Tensor) -> torch.Tensor:
    """BoQ in float64 from torch's building blocks: 3x3 projection, LayerNorm, per block
    an encoder layer, queries ``norm_q(q + self_attn(q))`` cross-attending to the tokens
    then ``norm_out``; outputs concatenated over queries, ``fc`` over queries,
    flattened ``channel * row_dim + row``, L2-normalised."""
    state = {k: v.double() for k, v in aggregator.state_dict().items()}
    width = state["norm_input.weight"].shape[0]
    heads = width // 64
    tokens = F.conv2d(x.double(), state["proj_c.weight"], state["proj_c.bias"], padding=1)
    tokens = F.layer_norm(
        tokens.flatten(2).transpose(1, 2),
        (width,),
        state["norm_input.weight"],
        state["norm_input.bias"],
    )
    outputs = []
    for i in range(len(aggregator.boqs)):
        block = {k[len(f"boqs.{i}.") :]: v for k, v in state.items() if k.startswith(f"boqs.{i}.")}
        encoder = nn.TransformerEncoderLayer(width, heads, 4 * width, dropout=0.0, batch_first=True)
        encoder.double().eval().load_state_dict(
            {k[len("encoder.") :]: v for k, v in block.items() if k.startswith("encoder.")}
        )
        attention = {}
        for name in ("self_attn", "cross_attn"):
            attention[name] = nn.MultiheadAttention(width, heads, batch_first=True).double()
            attention[name].load_state_dict(
                {k[len(name) + 1 :]: v for k, v in block.items() if k.startswith(name + ".")}
            )
        tokens = encoder(tokens)
        q = block["queries"].expand(x.shape[0], -1, -1)
        q = q + attention["self_attn"](q, q, q)[0]
        q = F.layer_norm(q, (width,), block["norm_q.weight"], block["norm_q.bias"])
        out = attention["cross_attn"](q, tokens, tokens)[0]
        outputs.append(
            F.layer_norm(out, (width,), block["norm_out.weight"], block["norm_out.bias"])
        )
    stacked = torch.cat(outputs, dim=1)  # [B, layers * queries, width]
    rows = torch.einsum("bqc,rq->bcr", stacked, state["fc.weight"]) + state["fc.bias"]
    return F.normalize(rows.reshape(x.shape[0], -1), dim=-1)


def test_aggregator_matches_float64_reference():
    aggregator = randomise(BoQAggregator(32, **SIZES), seed=6).double()
    x = torch.randn(2, 32, 3, 4, generator=_generator(7), dtype=torch.float64)
    with torch.no_grad():
        got = aggregator(x)
        expected = boq_reference(aggregator, x)
    assert got.shape == (2, 128 * 3)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)


def test_published_sizes():
    aggregator = BoQAggregator(768, proj_channels=PROJ_CHANNELS)
    assert aggregator.dim == 12288
    shapes = {k: tuple(v.shape) for k, v in aggregator.state_dict().items()}
    assert shapes["proj_c.weight"] == (384, 768, 3, 3)
    assert shapes["boqs.1.queries"] == (1, 64, 384)
    assert shapes["boqs.0.encoder.linear1.weight"] == (1536, 384)
    assert shapes["boqs.0.cross_attn.in_proj_weight"] == (1152, 384)
    assert shapes["fc.weight"] == (32, 128)
    assert aggregator.boqs[0].cross_attn.num_heads == 6
    assert len(aggregator.boqs) == 2


def _checkpoint(model: BoQDinoV2) -> dict[str, torch.Tensor]:
    state = prefixed(dinov2_hub_state_dict(model.backbone), "backbone.dino.")
    state.update(prefixed(model.aggregator.state_dict(), "aggregator."))
    return state


@pytest.fixture
def saved(tmp_path):
    source = randomise(BoQDinoV2(tiny_config(), **SIZES), seed=8)
    path = tmp_path / "dinov2_12288.pth"
    torch.save(_checkpoint(source), path)
    return source, path


def test_loaded_checkpoint_matches_float64_reference(saved):
    source, path = saved
    model = load_boq_dinov2(str(path), tiny_config(), **SIZES)
    images = torch.randn(2, 3, 70, 84, generator=_generator(9))
    patches, _ = vit_reference(
        dinov2_hub_state_dict(source.backbone), images, heads=2, final_norm=False
    )
    with torch.no_grad():
        expected = boq_reference(source.aggregator, patches)
        got = model(images)
        feature_map = model.feature_map(images)
    np.testing.assert_allclose(feature_map, patches.float(), rtol=0, atol=1e-4)
    np.testing.assert_allclose(got, expected.float(), rtol=0, atol=2e-6)
    # BoQ reads the last block's tokens: the final LayerNorm would change them.
    normed, _ = vit_reference(dinov2_hub_state_dict(source.backbone), images, heads=2)
    assert float((feature_map - normed.float()).abs().max()) > 1e-2


def test_missing_file_names_model_file_and_url(tmp_path):
    path = tmp_path / "absent.pth"
    with pytest.raises(CheckpointError) as error:
        load_boq_dinov2(str(path), tiny_config(), **SIZES)
    message = str(error.value)
    assert "BoQ-DINOv2" in message and str(path) in message and BOQ_DINOV2_URL in message


def test_mismatched_checkpoint_names_the_key(saved, tmp_path):
    source, _ = saved
    state = _checkpoint(source)
    del state["aggregator.boqs.1.norm_q.bias"]
    torch.save(state, tmp_path / "bad.pth")
    with pytest.raises(CheckpointError, match=r"aggregator\.boqs\.1\.norm_q\.bias"):
        load_boq_dinov2(str(tmp_path / "bad.pth"), tiny_config(), **SIZES)
    salad_like = {
        k.replace("backbone.dino.", "backbone.model."): v for k, v in _checkpoint(source).items()
    }
    torch.save(salad_like, tmp_path / "salad.pth")
    with pytest.raises(CheckpointError, match=r"backbone\.model\."):
        load_boq_dinov2(str(tmp_path / "salad.pth"), tiny_config(), **SIZES)
