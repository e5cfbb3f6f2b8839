"""SAM's mask decoder for many prompts on one image, sharing the image-side work.

transformers' ``SamMaskDecoder`` (and SAM-HQ's and SAM 2's, as the original libraries)
copies the ``[C, h, w]`` image embedding and its positional encoding once per prompt and
runs every projection of the two-way transformer on each copy. For automatic mask
generation (1,024 single-point prompts per image) that repetition is most of the time
after the image encoder. This module computes the same function with the products
re-associated so that nothing image-sized is repeated before it has to differ:

- the first block's token->image keys and values are projected once per image, not per
  prompt (its image->token queries are folded, as below);
- an attention whose ``N = h*w`` image tokens differ per prompt never projects them:
  with ``T`` prompt tokens and ``H`` heads, ``softmax(q (x W_k + b_k)^T) (x W_v + b_v)``
  is computed as ``softmax((q W_k) x^T) x W_v + b_v`` (``q b_k`` is constant along the
  softmax axis and cancels) and image->token attention folds the output projection into
  the ``T`` values, so per prompt each attention costs ``N x C x (H*T)`` multiply-adds
  instead of ``N x C x C/2`` per projection;
- the two transposed 2x2 convolutions of the mask upscaling (kernel = stride: each
  output pixel depends on one input pixel) are plain matrix products in a pixel-blocked
  layout, with the channel layer norm and GELUs applied in that layout, and the mask
  hypernetwork product is taken before one small re-ordering to image layout.

The arithmetic is the same function, so the outputs agree with transformers' decoder to
float32 rounding (tests: float64 to ~1e-12, float32 to ~1e-5 on random weights of the
published decoder size). Only what automatic mask generation uses is covered: point
prompts without mask inputs, ``multimask_output=True``, no attention similarity or
target embedding. Functions take the transformers modules and plain tensors; shapes are
per image: ``N = h*w`` image tokens, ``C`` channels, ``P`` prompts, ``T`` prompt tokens.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def _layer_norm(x: torch.Tensor, norm) -> torch.Tensor:
    return F.layer_norm(x, norm.normalized_shape, norm.weight, norm.bias, norm.eps)


def _out_projection(attention):
    """The attention's output projection (``out_proj`` in SAM / SAM-HQ, ``o_proj`` in SAM 2)."""
    return attention.out_proj if hasattr(attention, "out_proj") else attention.o_proj


def _heads(x: torch.Tensor, heads: int) -> torch.Tensor:
    """``[..., T, I]`` -> ``[..., heads, T, I / heads]``."""
    *lead, tokens, inner = x.shape
    return x.reshape(*lead, tokens, heads, inner // heads).transpose(-3, -2)


def _merge_heads(x: torch.Tensor) -> torch.Tensor:
    """``[..., heads, T, d]`` -> ``[..., T, heads * d]``."""
    *lead, heads, tokens, dim = x.shape
    return x.transpose(-3, -2).reshape(*lead, tokens, heads * dim)


def _softmax(scores: torch.Tensor, dim: int = -1) -> torch.Tensor:
    # At least float32 inside, cast back (as transformers' eager attention for bf16).
    wide = torch.promote_types(scores.dtype, torch.float32)
    return torch.softmax(scores.to(wide), dim=dim).to(scores.dtype)


def image_projections(attention, keys_pe, keys) -> tuple[torch.Tensor, torch.Tensor]:
    """Keys and values of a token->image attention over one image's ``[N, C]`` tokens ->
    ``([H, N, d], [H, N, d])`` (computed once per image, whatever the prompts)."""
    heads = attention.num_attention_heads
    return _heads(attention.k_proj(keys_pe), heads), _heads(attention.v_proj(keys), heads)


def token_to_image(attention, queries_pe, keys_pe, keys, projected=None) -> torch.Tensor:
    """Prompt tokens attending to the image -> the attention's output ``[P, T, C]``.

    ``queries_pe`` ``[P, T, C]``; ``keys_pe`` (keys plus positional encoding) and ``keys``
    are ``[N, C]`` (the same for every prompt: projected once, or pass ``projected`` from
    :func:`image_projections`) or ``[P, N, C]`` (projections re-associated onto the
    ``T`` query tokens).
    """
    heads = attention.num_attention_heads
    query = _heads(attention.q_proj(queries_pe), heads) * attention.scaling  # [P, H, T, d]
    prompts, _, tokens, dim = query.shape
    if keys.dim() == 2:
        # All prompts' tokens against the one image: [H, P*T, d] x [H, d, N].
        key, value = projected or image_projections(attention, keys_pe, keys)
        stacked = query.transpose(0, 1).reshape(heads, prompts * tokens, dim)
        weights = _softmax(stacked @ key.transpose(1, 2))  # [H, P*T, N]
        mixed = (weights @ value).view(heads, prompts, tokens, dim).transpose(0, 1)
    else:
        channels = keys.shape[-1]
        w_key = attention.k_proj.weight.view(heads, -1, channels)  # [H, d, C]
        w_value = attention.v_proj.weight.view(heads, -1, channels)
        folded = (query @ w_key).reshape(prompts, heads * tokens, channels)  # [P, H*T, C]
        weights = _softmax(folded @ keys_pe.transpose(1, 2))  # [P, H*T, N]
        pooled = (weights @ keys).view(prompts, heads, tokens, channels)
        mixed = pooled @ w_value.transpose(1, 2) + attention.v_proj.bias.view(heads, 1, -1)
    return _out_projection(attention)(_merge_heads(mixed))


def image_to_token(attention, keys_pe, queries_pe, queries, residual) -> torch.Tensor:
    """The image attending to the prompt tokens, plus ``residual`` -> ``[P, N, C]``.

    ``keys_pe`` and ``residual`` are ``[N, C]`` or ``[P, N, C]`` (a per-prompt
    ``residual`` is overwritten with the result); ``queries_pe`` and ``queries``
    ``[P, T, C]``. The image-side query projection is folded onto the ``T`` keys (its
    bias becomes a per-token score offset) and the output projection onto the ``T``
    values (its bias spread over the ``H`` heads' weights, which sum to ``H``), so the
    only image-sized products are ``[N, C] x [C, H*T]`` and back.
    """
    heads = attention.num_attention_heads
    out = _out_projection(attention)
    prompts, tokens, channels = queries.shape
    key = _heads(attention.k_proj(queries_pe), heads) * attention.scaling  # [P, H, T, d]
    w_query = attention.q_proj.weight.view(heads, -1, channels)  # [H, d, C]
    folded = (key @ w_query).reshape(prompts, heads * tokens, channels)  # [P, H*T, C]
    offset = (key @ attention.q_proj.bias.view(heads, -1, 1)).reshape(prompts, heads * tokens, 1)
    # Scores as [P, H*T, N]: the softmax over each head's T tokens then runs along a
    # strided axis with N contiguous, far faster than over a last axis of length T.
    if keys_pe.dim() == 2:
        scores = (folded.reshape(-1, channels) @ keys_pe.T).view(prompts, heads * tokens, -1)
    else:
        scores = folded @ keys_pe.transpose(1, 2)
    scores += offset
    size = scores.shape[-1]
    weights = _softmax(scores.view(prompts, heads, tokens, size), dim=2)
    weights = weights.view(prompts, heads * tokens, size)
    value = _heads(attention.v_proj(queries), heads)  # [P, H, T, d]
    w_out = out.weight.view(channels, heads, -1).permute(1, 2, 0)  # [H, d, C]
    projected = (value @ w_out).reshape(prompts, heads * tokens, channels) + out.bias / heads
    if residual.dim() == 2:
        return torch.baddbmm(residual.expand(prompts, *residual.shape), weights.mT, projected)
    return residual.baddbmm_(weights.mT, projected)


def _self_attention(attention, query, value) -> torch.Tensor:
    """transformers' attention module on one image's ``[P, T, C]`` tokens."""
    return attention(query=query[None], key=query[None], value=value[None])[0][0]


def image_side(transformer, image, image_pe):
    """What the first block reads of the image alone, computed once per image:
    ``(image + image_pe [N, C], its token->image attention's keys and values)``."""
    keys_pe = image + image_pe
    attention = transformer.layers[0].cross_attn_token_to_image
    return keys_pe, image_projections(attention, keys_pe, image)


def two_way_transformer(transformer, image, image_pe, tokens, first=None):
    """SAM's two-way transformer for ``P`` prompts on one image.

    ``image`` and ``image_pe`` ``[N, C]`` (embedding plus dense prompt, positional
    encoding); ``tokens`` ``[P, T, C]`` (output tokens then sparse prompt embeddings)
    -> ``(queries [P, T, C], keys [P, N, C])`` as ``transformer(...)`` returns them.
    ``first``: the image's :func:`image_side`, when already computed.
    """
    queries, keys = tokens, image
    keys_pe, projected = first or image_side(transformer, image, image_pe)
    for layer in transformer.layers:
        if layer.skip_first_layer_pe:
            queries = _self_attention(layer.self_attn, queries, queries)
        else:
            queries = queries + _self_attention(layer.self_attn, queries + tokens, queries)
        queries = _layer_norm(queries, layer.layer_norm1)
        if keys.dim() == 3:  # keys differ per prompt from the first block's output on
            keys_pe, projected = keys + image_pe, None
        attended = token_to_image(
            layer.cross_attn_token_to_image, queries + tokens, keys_pe, keys, projected
        )
        queries = _layer_norm(queries + attended, layer.layer_norm2)
        queries = _layer_norm(queries + layer.mlp(queries), layer.layer_norm3)
        keys = image_to_token(
            layer.cross_attn_image_to_token, keys_pe, queries + tokens, queries, residual=keys
        )
        keys = _layer_norm(keys, layer.layer_norm4)
    attended = token_to_image(
        transformer.final_attn_token_to_image, queries + tokens, keys + image_pe, keys
    )
    return _layer_norm(queries + attended, transformer.layer_norm_final_attn), keys


def _chunked(decode_tokens, transformer, image, image_pe, tokens, chunk):
    """``decode_tokens(queries, keys)`` over the prompts ``chunk`` at a time (all at once
    for ``None``) -> its outputs concatenated.

    On a CPU small chunks keep one chunk's image-sized intermediates (~17 MB per prompt
    in float32) in the last-level cache; :func:`image_side` is shared by all chunks.
    """
    first = image_side(transformer, image, image_pe)
    step = chunk or tokens.shape[0]
    outputs = [
        decode_tokens(*two_way_transformer(transformer, image, image_pe, part, first))
        for part in tokens.split(step)
    ]
    return tuple(torch.cat(parts) for parts in zip(*outputs, strict=True))


def blocked(feature: torch.Tensor, levels: int) -> torch.Tensor:
    """Image-layout features ``[c, 2^levels h, 2^levels w]`` -> the pixel-blocked layout
    ``[h*w, 4^levels, c]`` that :func:`upscale` works in (row-major over the low-res
    pixel, then over the 2x2 sub-pixels of each upscaling level, coarsest first)."""
    channels, height, width = feature.shape
    h, w = height >> levels, width >> levels
    view = feature.reshape(channels, h, *[2] * levels, w, *[2] * levels)
    # dims: c, y, i_1..i_L, x, j_1..j_L -> y, x, (i_1, j_1), ..., (i_L, j_L), c
    rows = list(range(2, 2 + levels))
    cols = list(range(3 + levels, 3 + 2 * levels))
    pairs = [d for pair in zip(rows, cols, strict=True) for d in pair]
    order = [1, 2 + levels, *pairs, 0]
    return view.permute(order).reshape(h * w, 4**levels, channels)


def unblocked(
    blocked_values: torch.Tensor, height: int, width: int, channels_last: bool = False
) -> torch.Tensor:
    """Two-level pixel-blocked values ``[P, h*w, 16, M]`` -> image layout ``[P, M, 4h, 4w]``
    (with ``channels_last``, strided as PyTorch's channels-last format)."""
    prompts, _, _, masks = blocked_values.shape
    view = blocked_values.view(prompts, height, width, 2, 2, 2, 2, masks)  # y x i j k l m
    if channels_last:
        pixels = view.permute(0, 1, 3, 5, 2, 4, 6, 7).reshape(prompts, 4 * height, 4 * width, masks)
        return pixels.permute(0, 3, 1, 2)
    return view.permute(0, 7, 1, 3, 5, 2, 4, 6).reshape(prompts, masks, 4 * height, 4 * width)


def _transposed_2x2(conv) -> tuple[torch.Tensor, torch.Tensor]:
    """A ``ConvTranspose2d`` with kernel = stride = 2 as ``[4 * C_out, C_in]`` weights and
    bias for ``F.linear``, output ordered (sub-pixel row, sub-pixel column, channel)."""
    if tuple(conv.kernel_size) != (2, 2) or tuple(conv.stride) != (2, 2):
        raise ValueError(f"expected a 2x2 stride-2 transposed convolution, got {conv}")
    weight = conv.weight.permute(2, 3, 1, 0).reshape(-1, conv.weight.shape[0])
    return weight, conv.bias.repeat(4)


def upscale(decoder, keys, height: int, width: int, high_res=None) -> torch.Tensor:
    """The decoder's mask upscaling of per-prompt keys ``[P, N, C]`` -> pixel-blocked
    features ``[P, N, 16, C/8]`` (image layout: :func:`unblocked`).

    ``conv2(act(norm(conv1(x) + s1))) + s0`` then ``act``, as transformers'
    ``upscale_conv1`` / ``upscale_layer_norm`` / ``upscale_conv2``; ``high_res`` is SAM 2's
    ``(s0, s1)`` in the blocked layout (``[N, 16, C/8]``, ``[N, 4, C/4]``) or ``None``.
    """
    prompts, size, _ = keys.shape
    weight, bias = _transposed_2x2(decoder.upscale_conv1)
    hidden = F.linear(keys, weight, bias).view(prompts, size, 4, -1)  # [P, N, 4, C/4]
    if high_res is not None:
        hidden = hidden + high_res[1]
    hidden = decoder.activation(_layer_norm(hidden, decoder.upscale_layer_norm))
    weight, bias = _transposed_2x2(decoder.upscale_conv2)
    upscaled = F.linear(hidden, weight, bias).view(prompts, size, 16, -1)  # [P, N, 16, C/8]
    if high_res is not None:
        upscaled = upscaled + high_res[0]
    return decoder.activation(upscaled)


def _hyper(decoder, mask_tokens: torch.Tensor, indices) -> torch.Tensor:
    """Hypernetwork outputs of the mask tokens ``indices`` -> ``[P, len(indices), C/8]``."""
    mlps = decoder.output_hypernetworks_mlps
    return torch.stack([mlps[i](mask_tokens[:, i]) for i in indices], dim=1)


def _masks(upscaled: torch.Tensor, hyper: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Blocked features ``[P, N, 16, c]`` and hypernetwork ``[P, M, c]`` -> ``[P, M, 4h, 4w]``."""
    prompts, size = upscaled.shape[:2]
    values = upscaled.view(prompts, size * 16, -1) @ hyper.transpose(1, 2)
    return unblocked(values.view(prompts, size, 16, -1), height, width)


def _tokens(output: torch.Tensor, sparse: torch.Tensor, dtype) -> torch.Tensor:
    """Output tokens ``[O, C]`` and sparse prompts ``[1, P, S, C]`` -> ``[P, O + S, C]``."""
    sparse = sparse[0]
    return torch.cat([output.expand(sparse.shape[0], -1, -1), sparse], dim=1).to(dtype)


def _image_tokens(embedding: torch.Tensor, dense: torch.Tensor, image_pe: torch.Tensor):
    """``[1, C, h, w]`` embedding, dense prompt and positional encoding -> ``[N, C]`` twice."""
    if embedding.shape[0] != 1 or dense.shape[0] != 1 or image_pe.shape[0] != 1:
        raise ValueError("one image at a time: batch dimension must be 1")
    image = (embedding + dense)[0].flatten(1).transpose(0, 1)
    return image, image_pe[0].flatten(1).transpose(0, 1).to(image.dtype)


def decode_sam(decoder, embedding, image_pe, sparse, dense, chunk=None):
    """``SamMaskDecoder`` with ``multimask_output=True``, one image.

    ``embedding`` ``[1, C, h, w]``, ``image_pe`` ``[1, C, h, w]``, ``sparse`` ``[1, P, S, C]``,
    ``dense`` ``[1, C, h, w]`` -> low-res logits ``[P, 3, 4h, 4w]`` and IoUs ``[P, 3]``.
    ``chunk``: prompts per pass (``None``: all).
    """
    height, width = embedding.shape[-2:]
    image, pe = _image_tokens(embedding, dense, image_pe)
    output = torch.cat([decoder.iou_token.weight, decoder.mask_tokens.weight])
    tokens = _tokens(output, sparse, image.dtype)
    selected = range(1, decoder.num_mask_tokens)

    def decode_tokens(queries, keys):
        mask_tokens = queries[:, 1 : 1 + decoder.num_mask_tokens]
        upscaled = upscale(decoder, keys, height, width)
        masks = _masks(upscaled, _hyper(decoder, mask_tokens, selected), height, width)
        return masks, decoder.iou_prediction_head(queries[:, 0])[:, 1:]

    return _chunked(decode_tokens, decoder.transformer, image, pe, tokens, chunk)


def decode_sam2(decoder, embeddings, image_pe, sparse, dense, chunk=None):
    """``Sam2MaskDecoder`` with ``multimask_output=True``, one image.

    ``embeddings``: the model's ``get_image_embeddings`` list (high-resolution levels
    first, ``[1, C/8, 4h, 4w]`` and ``[1, C/4, 2h, 2w]``, then ``[1, C, h, w]``); other
    arguments as :func:`decode_sam` -> logits ``[P, 3, 4h, 4w]``, IoUs ``[P, 3]``.
    """
    *high_res, embedding = embeddings
    height, width = embedding.shape[-2:]
    image, pe = _image_tokens(embedding, dense, image_pe)
    feat_s0, feat_s1 = high_res
    blocked_high_res = (blocked(feat_s0[0], 2), blocked(feat_s1[0], 1))
    output = torch.cat(
        [decoder.obj_score_token.weight, decoder.iou_token.weight, decoder.mask_tokens.weight]
    )
    tokens = _tokens(output, sparse, image.dtype)
    selected = range(1, decoder.num_mask_tokens)

    def decode_tokens(queries, keys):
        mask_tokens = queries[:, 2 : 2 + decoder.num_mask_tokens]
        upscaled = upscale(decoder, keys, height, width, blocked_high_res)
        masks = _masks(upscaled, _hyper(decoder, mask_tokens, selected), height, width)
        return masks, decoder.iou_prediction_head(queries[:, 1])[:, 1:]

    return _chunked(decode_tokens, decoder.transformer, image, pe, tokens, chunk)


def decode_sam_hq(
    decoder, embedding, intermediate, image_pe, sparse, dense, hq_token_only, chunk=None
):
    """``SamHQMaskDecoder`` with ``multimask_output=True``, one image, as SAM-HQ's
    automatic generator reads it: the best of SAM's three masks (highest predicted IoU)
    plus the HQ mask (or the HQ mask alone) -> logits ``[P, 1, 4h, 4w]``, IoUs ``[P, 1]``.

    ``intermediate``: the model's early ViT features (``get_image_embeddings``' second
    output). The HQ branch's 3x3 convolutions run on image-layout features per prompt
    (they are most of its cost and cannot be shared); its image-only features once.
    Masks are upscaled from the two-way transformer's output, as the original
    ``MaskDecoderHQ`` (transformers' ``SamHQMaskDecoder`` upscales its input instead).
    """
    height, width = embedding.shape[-2:]
    vit = intermediate[0].permute(0, 3, 1, 2)
    encoded = decoder.encoder_conv2(
        decoder.activation(decoder.encoder_norm(decoder.encoder_conv1(embedding)))
    )
    compressed = decoder.compress_vit_conv2(
        decoder.activation(decoder.compress_vit_norm(decoder.compress_vit_conv1(vit)))
    )
    hq_features = encoded + compressed  # [1, C/8, 4h, 4w]

    image, pe = _image_tokens(embedding, dense, image_pe)
    output = torch.cat(
        [decoder.iou_token.weight, decoder.mask_tokens.weight, decoder.hq_token.weight]
    )
    tokens = _tokens(output, sparse, image.dtype)
    sam_tokens = decoder.num_mask_tokens - 1  # transformers counts the HQ token in

    def decode_tokens(queries, keys):
        iou = decoder.iou_prediction_head(queries[:, 0])[:, 1:sam_tokens]  # [P, 3]
        best_iou, best = iou.max(dim=1)
        upscaled = upscale(decoder, keys, height, width)
        # Channels-last: the 3x3 convolutions run ~1.4x faster on a CPU (oneDNN).
        image_layout = unblocked(upscaled, height, width, channels_last=True)
        hq = decoder.mask_conv2(
            decoder.activation(decoder.mask_norm(decoder.mask_conv1(image_layout)))
        )
        hq = hq + hq_features
        hq_hyper = decoder.hq_mask_mlp(queries[:, 1 + sam_tokens])  # [P, C/8]
        masks = torch.einsum("pc,pchw->phw", hq_hyper, hq)[:, None]
        if not hq_token_only:
            mask_tokens = queries[:, 1 : 1 + sam_tokens]
            hypers = _hyper(decoder, mask_tokens, range(1, sam_tokens))  # [P, 3, C/8]
            chosen = hypers[torch.arange(len(best), device=best.device), best][:, None]
            masks = masks + _masks(upscaled, chosen, height, width)
        return masks, best_iou[:, None]

    return _chunked(decode_tokens, decoder.transformer, image, pe, tokens, chunk)
