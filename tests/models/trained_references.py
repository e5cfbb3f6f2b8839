"""Float64 references for the trained VPR models' tests, written from the papers' and
original repositories' equations (not from vprflow's modules): a DINOv2 ViT forward
from torch-hub-named weights, SALAD's Sinkhorn and aggregation, and a weight
randomiser that leaves no block near the identity.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch.nn import functional as F

from vprflow.models.trunks.dinov2 import dinov2_config

TINY_VIT = {"hidden_size": 32, "num_hidden_layers": 2, "num_attention_heads": 2, "image_size": 56}


def tiny_config(**overrides):
    """A 2-block, 32-wide DINOv2 with a 4 x 4 stored position grid (56 px, patch 14)."""
    return dinov2_config(**{**TINY_VIT, **overrides})


def randomise(module: torch.nn.Module, seed: int) -> torch.nn.Module:
    """Re-draw every parameter: He-scaled weights, small biases, norms and layer scales
    near 1, tokens O(1)."""
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, parameter in module.named_parameters():
            noise = torch.randn(parameter.shape, generator=generator, dtype=torch.float64)
            leaf = name.rpartition(".")[2]
            if parameter.ndim == 0 or leaf in ("gamma", "lambda1"):
                value = 1.0 + 0.2 * noise
            elif "norm" in name:
                value = (1.0 if leaf == "weight" else 0.0) + 0.1 * noise
            elif parameter.ndim == 1:
                value = 0.1 * noise
            elif leaf.endswith("token") or "position" in leaf or leaf in ("queries", "centroids"):
                value = 0.5 * noise
            else:
                value = noise * math.sqrt(2.0 / parameter[0].numel())
            parameter.copy_(value.to(parameter.dtype))
    return module.eval()


def _layer_norm(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, eps: float):
    mean = x.mean(-1, keepdim=True)
    var = ((x - mean) ** 2).mean(-1, keepdim=True)
    return (x - mean) / torch.sqrt(var + eps) * weight + bias


def vit_reference(
    hub: dict[str, torch.Tensor],
    images: torch.Tensor,
    *,
    heads: int,
    patch: int = 14,
    final_norm: bool = True,
    eps: float = 1e-6,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The facebookresearch/dinov2 ViT in float64 from torch-hub-named weights ``hub``:
    ``images`` ``[B, 3, H, W]`` -> ``(patches [B, C, H/p, W/p], cls [B, C])``.

    Position embeddings: the stored ``M x M`` grid resized bicubically with scale factor
    ``((rows + 0.1) / M, (cols + 0.1) / M)``, unless the grid already fits a square input.
    Blocks: ``x += ls1 * proj(attn(norm1(x)))``; ``x += ls2 * fc2(gelu(fc1(norm2(x))))``.
    """
    w = {k: v.double() for k, v in hub.items()}
    batch, _, height, width = images.shape
    rows, cols = height // patch, width // patch
    x = F.conv2d(
        images.double(), w["patch_embed.proj.weight"], w["patch_embed.proj.bias"], stride=patch
    )
    x = x.flatten(2).transpose(1, 2)
    x = torch.cat([w["cls_token"].expand(batch, -1, -1), x], dim=1)
    stored = w["pos_embed"]
    side = math.isqrt(stored.shape[1] - 1)
    dim = stored.shape[-1]
    if (rows, cols) == (side, side):
        pos = stored
    else:
        grid = stored[:, 1:].reshape(1, side, side, dim).permute(0, 3, 1, 2)
        grid = F.interpolate(
            grid, scale_factor=((rows + 0.1) / side, (cols + 0.1) / side), mode="bicubic"
        )
        pos = torch.cat([stored[:, :1], grid.permute(0, 2, 3, 1).reshape(1, rows * cols, dim)], 1)
    x = x + pos
    blocks = sorted({int(k.split(".")[1]) for k in w if k.startswith("blocks.")})
    head_dim = dim // heads
    for i in blocks:
        b = f"blocks.{i}."
        h = _layer_norm(x, w[b + "norm1.weight"], w[b + "norm1.bias"], eps)
        qkv = h @ w[b + "attn.qkv.weight"].T + w[b + "attn.qkv.bias"]
        q, k, v = (
            part.reshape(batch, -1, heads, head_dim).transpose(1, 2) for part in qkv.chunk(3, -1)
        )
        attention = torch.softmax(q @ k.transpose(-2, -1) / math.sqrt(head_dim), dim=-1)
        out = (attention @ v).transpose(1, 2).reshape(batch, -1, dim)
        x = x + w[b + "ls1.gamma"] * (out @ w[b + "attn.proj.weight"].T + w[b + "attn.proj.bias"])
        h = _layer_norm(x, w[b + "norm2.weight"], w[b + "norm2.bias"], eps)
        h = F.gelu(h @ w[b + "mlp.fc1.weight"].T + w[b + "mlp.fc1.bias"])
        x = x + w[b + "ls2.gamma"] * (h @ w[b + "mlp.fc2.weight"].T + w[b + "mlp.fc2.bias"])
    if final_norm:
        x = _layer_norm(x, w["norm.weight"], w["norm.bias"], eps)
    patches = x[:, 1:].reshape(batch, rows, cols, dim).permute(0, 3, 1, 2)
    return patches, x[:, 0]


def _logsumexp(a: np.ndarray, axis: int) -> np.ndarray:
    top = a.max(axis=axis, keepdims=True)
    return (top + np.log(np.exp(a - top).sum(axis=axis, keepdims=True))).squeeze(axis)


def sinkhorn_reference(scores: np.ndarray, dust_bin: float, iterations: int) -> np.ndarray:
    """SALAD's log transport plan for one image: ``scores`` ``[m, n]`` -> ``[m + 1, n]``
    (a dustbin row of ``dust_bin``; marginals ``1/(n+m)`` per cluster and column,
    ``(n-m)/(n+m)`` for the dustbin; result scaled by ``n + m``)."""
    m, n = scores.shape
    s = np.vstack([scores, np.full((1, n), dust_bin)])
    log_a = np.full(m + 1, -np.log(n + m))
    log_a[-1] += np.log(n - m)
    log_b = np.full(n, -np.log(n + m))
    u, v = np.zeros(m + 1), np.zeros(n)
    for _ in range(iterations):
        u = log_a - _logsumexp(s + v[None, :], axis=1)
        v = log_b - _logsumexp(s + u[:, None], axis=0)
    return s + u[:, None] + v[None, :] + np.log(n + m)


def _mlp_1x1(x: np.ndarray, w: dict, name: str) -> np.ndarray:
    """SALAD's ``Conv1x1 -> ReLU -> Conv1x1`` on ``x`` ``[C, n]`` (indices 0 and 3)."""
    h = w[f"{name}.0.weight"][:, :, 0, 0] @ x + w[f"{name}.0.bias"][:, None]
    h = np.maximum(h, 0)
    return w[f"{name}.3.weight"][:, :, 0, 0] @ h + w[f"{name}.3.bias"][:, None]


def salad_reference(state: dict[str, torch.Tensor], x: torch.Tensor, t: torch.Tensor):
    """SALAD's descriptor in float64 from its aggregator weights ``state`` (keys without
    prefix): ``x`` ``[B, C, h, w]``, ``t`` ``[B, C]`` -> ``[B, g + l * m]``, cluster
    block ordered ``c * m + k``."""
    w = {k: v.double().numpy() for k, v in state.items()}
    out = []
    for feats, token in zip(x.double().numpy(), t.double().numpy(), strict=True):
        points = feats.reshape(feats.shape[0], -1)
        f = _mlp_1x1(points, w, "cluster_features")  # [l, n]
        s = _mlp_1x1(points, w, "score")  # [m, n]
        p = np.exp(sinkhorn_reference(s, float(w["dust_bin"]), 3))[:-1]  # [m, n]
        v = f @ p.T  # [l, m]
        v = v / np.linalg.norm(v, axis=0, keepdims=True)
        g = np.maximum(w["token_features.0.weight"] @ token + w["token_features.0.bias"], 0)
        g = w["token_features.2.weight"] @ g + w["token_features.2.bias"]
        d = np.concatenate([g / np.linalg.norm(g), v.reshape(-1)])
        out.append(d / np.linalg.norm(d))
    return torch.from_numpy(np.stack(out))


def prefixed(state: dict[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    return {prefix + k: v.clone() for k, v in state.items()}


def vlad_buff_reference(state: dict[str, torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """VLAD-BuFF's VLAD in float64 (Khaliq et al., ECCV 2024, eqs. of §3) from its
    aggregator weights ``state`` (keys without prefix): ``x`` ``[B, C, h, w]`` ->
    ``[B, K * D]``. Each patch unit-length (then, with ``pca_rot`` ``R`` and
    ``pca_mean`` ``mu``, ``L2(R (x - mu))``); ``a_ki = softmax_k(W_k . x_i)``; burst
    weight ``w_i = (sum_j sigmoid(alpha (2 x_i . x_j - 2) + beta)) ** p``;
    ``V_k = sum_i (a_ki / w_i) (x_i - c_k)``, each ``V_k`` unit-length, flattened
    ``k * D + d``, unit-length."""
    w = {k: v.double().numpy() for k, v in state.items()}
    alpha, beta, power = w["ab_params"]
    weights, centroids = w["conv.weight"][:, :, 0, 0], w["centroids"]
    out = []
    for feats in x.double().numpy():
        points = feats.reshape(feats.shape[0], -1)  # [C, n]
        points = points / np.linalg.norm(points, axis=0, keepdims=True)
        if "pca_rot" in w:
            points = w["pca_rot"] @ (points - w["pca_mean"][:, None])
            points = points / np.linalg.norm(points, axis=0, keepdims=True)
        logits = weights @ points  # [K, n]
        assign = np.exp(logits - logits.max(axis=0))
        assign /= assign.sum(axis=0)
        similarity = 2 * points.T @ points - 2
        burst = (1 / (1 + np.exp(-(alpha * similarity + beta)))).sum(axis=1) ** power
        assign = assign / burst[None, :]
        vlad = np.stack(
            [
                (assign[k][None, :] * (points - centroids[k][:, None])).sum(axis=1)
                for k in range(len(centroids))
            ]
        )  # [K, D]
        vlad = vlad / np.linalg.norm(vlad, axis=1, keepdims=True)
        vlad = vlad.reshape(-1)
        out.append(vlad / np.linalg.norm(vlad))
    return torch.from_numpy(np.stack(out))


def whitening_reference(weight: torch.Tensor, bias: torch.Tensor, v: torch.Tensor):
    """A whitening PCA stored as a 1x1 convolution ``weight`` ``[P, D, 1, 1]``, ``bias``
    ``[P]``, on descriptors ``v`` ``[B, D]``, in float64: ``L2(U v + b)``."""
    u = weight.double().numpy()[:, :, 0, 0]
    out = v.double().numpy() @ u.T + bias.double().numpy()
    return torch.from_numpy(out / np.linalg.norm(out, axis=1, keepdims=True))
