"""SAM's mask decoder for a grid of single-point prompts, with the per-image work done once.

``transformers.SamMaskDecoder`` copies the image embedding and its positional encoding once per
prompt and runs every projection of the two-way transformer on those copies, then upsamples the
[P, 256, 64, 64] result with two transposed convolutions in channels-first layout. For the
automatic generator's 1024 prompts most of that is shared or reorderable:

* in the first block, the image side is the same for every prompt: the token->image keys and
  values and the image->token queries are projected once per image (3 of the 10 image-sized
  projections);
* the image embedding stays token-major [P, 4096, C] throughout: a 2x2 stride-2 transposed
  convolution is one matrix product per input pixel, its channel LayerNorm a plain last-axis
  LayerNorm, so nothing is permuted until the final [P, 256, 256] logits;
* only the one mask level the generator keeps goes through its hypernetwork and the final product.

The weights are the ``SamModel``'s own modules (:class:`SamGridDecoder` holds no parameters); the
result equals ``SamModel(image_embeddings=..., input_points=..., multimask_output=True)`` up to
float rounding (tests/language/test_sam_decoder.py). ``autocast`` runs the matrix products in
bfloat16 (LayerNorm and softmax stay float32, as under ``torch.autocast``).
"""
from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F


@dataclass
class ImageTokens:
    """Per-image decoder inputs, shared by every prompt batch of the image (L = 64 x 64 tokens).

    src [L, C]: the embedding plus the no-mask dense prompt; pe [L, C]: its positional encoding;
    key0 / value0 [L, C/2]: the first block's token->image key and value; query0 [L, C/2]: its
    image->token query; grid (h, w) of the tokens."""

    src: torch.Tensor
    pe: torch.Tensor
    key0: torch.Tensor
    value0: torch.Tensor
    query0: torch.Tensor
    grid: tuple[int, int]


def _split_heads(x: torch.Tensor, heads: int) -> torch.Tensor:
    """[..., T, D] -> [..., heads, T, D / heads]."""
    *lead, t, d = x.shape
    return x.reshape(*lead, t, heads, d // heads).transpose(-3, -2)


def _attend(attn: Any, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """SamAttention on projected q [..., Tq, D], k, v [..., Tk, D] (leading dims broadcast), then
    ``out_proj``: [..., Tq, C]. Scaled dot-product attention as transformers' SAM runs it."""
    heads = attn.num_attention_heads
    qh, kh, vh = _split_heads(q, heads), _split_heads(k, heads), _split_heads(v, heads)
    lead = torch.broadcast_shapes(qh.shape[:-3], kh.shape[:-3], vh.shape[:-3])
    qh, kh, vh = (t.expand(*lead, *t.shape[-3:]) for t in (qh, kh, vh))
    out = F.scaled_dot_product_attention(qh, kh, vh, scale=attn.scaling)  # [..., heads, Tq, d]
    return attn.out_proj(out.transpose(-3, -2).flatten(-2))


def _attend_shared_keys(attn: Any, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """:func:`_attend` for queries q [P, T, D] of P prompts against keys and values k, v [L, D]
    shared by all prompts: one attention call over the P * T queries. Returns [P, T, C]."""
    p, t, d = q.shape
    return _attend(attn, q.reshape(1, p * t, d), k[None], v[None]).view(p, t, -1)


def _project_attend(attn: Any, query: torch.Tensor, key: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
    """SamAttention on unprojected inputs (its own q/k/v projections, then :func:`_attend`)."""
    return _attend(attn, attn.q_proj(query), attn.k_proj(key), attn.v_proj(value))


def _conv_t2x2_as_linear(conv: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """A ConvTranspose2d(k=2, s=2) [Cin, Cout, 2, 2] as a linear map Cin -> (i, j, Cout): output
    pixel (2y + i, 2x + j) of input pixel (y, x). Returns (weight [4 Cout, Cin], bias [4 Cout])."""
    w = conv.weight  # [Cin, Cout, 2, 2]
    cin, cout = w.shape[:2]
    return w.permute(2, 3, 1, 0).reshape(4 * cout, cin), conv.bias.repeat(4)


class SamGridDecoder:
    """Low-resolution logits and predicted IoU of one multimask ``level`` for single positive point
    prompts, on a ``transformers.SamModel``'s weights.

    ``prepare(embedding [1, C, h, w]) -> ImageTokens`` once per image, then
    ``decoder(tokens, points [P, 2]) -> (logits [P, 4h, 4w] float32, iou [P] float32)`` per batch,
    points (x, y) in pixels of SAM's input frame.
    """

    def __init__(self, model: Any, level: int = 0, autocast: bool = False) -> None:
        dec = model.mask_decoder
        if not 0 <= level < dec.num_multimask_outputs:
            raise ValueError(f"tiger.SamGridDecoder: level must be in [0, {dec.num_multimask_outputs}), got {level}")
        self.model = model
        self.level = level
        self.autocast = autocast

    def _context(self, device: torch.device):
        if not self.autocast:
            return nullcontext()
        return torch.autocast(device_type=device.type, dtype=torch.bfloat16)

    @torch.no_grad()
    def prepare(self, embedding: torch.Tensor) -> ImageTokens:
        """The prompt-independent part of the decoder for image embedding [1, C, h, w]."""
        if embedding.dim() != 4 or embedding.shape[0] != 1:
            raise ValueError(f"tiger.SamGridDecoder: embedding must be [1, C, h, w], got {tuple(embedding.shape)}")
        model = self.model
        dense = model.prompt_encoder.no_mask_embed.weight.reshape(1, -1, 1, 1)
        src = (embedding + dense)[0].flatten(1).T  # [L, C], token t = y * w + x as transformers flattens
        pe = model.get_image_wide_positional_embeddings()[0].flatten(1).T.to(src.dtype)
        block = model.mask_decoder.transformer.layers[0]
        with self._context(embedding.device):
            key = src + pe
            key0 = block.cross_attn_token_to_image.k_proj(key)
            value0 = block.cross_attn_token_to_image.v_proj(src)
            query0 = block.cross_attn_image_to_token.q_proj(key)
        return ImageTokens(src, pe, key0, value0, query0, tuple(embedding.shape[-2:]))

    def _tokens(self, points: torch.Tensor) -> torch.Tensor:
        """Decoder tokens [P, 7, C]: IoU token, 4 mask tokens, the point and SAM's padding point."""
        model = self.model
        p = points.shape[0]
        labels = torch.ones(1, p, 1, dtype=torch.int64, device=points.device)
        sparse, _ = model.prompt_encoder(input_points=points[None, :, None, :], input_labels=labels,
                                         input_boxes=None, input_masks=None)  # [1, P, 2, C]
        dec = model.mask_decoder
        out_tokens = torch.cat([dec.iou_token.weight, dec.mask_tokens.weight], dim=0)
        return torch.cat([out_tokens.expand(p, -1, -1), sparse[0].to(out_tokens.dtype)], dim=1)

    @torch.no_grad()
    def __call__(self, image: ImageTokens, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        dec = self.model.mask_decoder
        with self._context(points.device):
            tokens = self._tokens(points)
            queries, keys = self._transformer(image, tokens)
            logits = self._masks(keys, queries[:, 2 + self.level], image.grid)
            iou = dec.iou_prediction_head(queries[:, 0])[:, 1 + self.level]
        return logits.float(), iou.float()

    def _transformer(self, image: ImageTokens, tokens: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """SamTwoWayTransformer for P prompts: (queries [P, 7, C], keys [P, L, C])."""
        tr = self.model.mask_decoder.transformer
        qpe = tokens
        queries = tokens
        keys = None  # [P, L, C] once the first block has written per-prompt image tokens
        for index, block in enumerate(tr.layers):
            if block.skip_first_layer_pe:
                queries = _project_attend(block.self_attn, queries, queries, queries)
            else:
                q = queries + qpe
                queries = queries + _project_attend(block.self_attn, q, q, queries)
            queries = block.layer_norm1(queries)
            t2i, i2t = block.cross_attn_token_to_image, block.cross_attn_image_to_token
            q = t2i.q_proj(queries + qpe)
            if keys is None:  # first block: the image side is the same for every prompt
                attn = _attend_shared_keys(t2i, q, image.key0, image.value0)
            else:
                keys_pe = keys + image.pe
                attn = _attend(t2i, q, t2i.k_proj(keys_pe), t2i.v_proj(keys))
            queries = block.layer_norm2(queries + attn)
            queries = block.layer_norm3(queries + block.mlp(queries))
            q = queries + qpe
            tk, tv = i2t.k_proj(q), i2t.v_proj(queries)
            if keys is None:
                update = _attend(i2t, image.query0, tk, tv)  # [P, L, C]
                keys = block.layer_norm4(image.src + update)
            else:
                update = _attend(i2t, i2t.q_proj(keys_pe), tk, tv)
                del keys_pe
                keys = block.layer_norm4(keys + update)
            del update
        if keys is None:  # a decoder without blocks: the image tokens as they came
            keys = image.src.expand(tokens.shape[0], -1, -1)
        fin = tr.final_attn_token_to_image
        attn = _attend(fin, fin.q_proj(queries + qpe), fin.k_proj(keys + image.pe), fin.v_proj(keys))
        queries = tr.layer_norm_final_attn(queries + attn)
        return queries, keys

    def _masks(self, keys: torch.Tensor, mask_token: torch.Tensor, grid: tuple[int, int]) -> torch.Tensor:
        """Upscaled embedding . hypernetwork(mask token): logits [P, 4h, 4w] of keys [P, h*w, C]."""
        dec = self.model.mask_decoder
        p, length, _ = keys.shape
        h, w = grid
        w1, b1 = _conv_t2x2_as_linear(dec.upscale_conv1)
        x = F.linear(keys, w1, b1)  # [P, L, (i, j, C/4)]
        c4 = w1.shape[0] // 4
        norm = dec.upscale_layer_norm
        x = dec.activation(F.layer_norm(x.view(p, length * 4, c4), (c4,), norm.weight, norm.bias, norm.eps))
        w2, b2 = _conv_t2x2_as_linear(dec.upscale_conv2)
        x = dec.activation(F.linear(x, w2, b2))  # [P, L * 4, (I, J, C/8)]
        c8 = w2.shape[0] // 4
        hyper = dec.output_hypernetworks_mlps[1 + self.level](mask_token)  # [P, C/8]
        m = torch.matmul(x.view(p, length * 16, c8), hyper[:, :, None].to(x.dtype))  # [P, L * 16, 1]
        # (y, x, i, j, I, J) -> row 4y + 2i + I, column 4x + 2j + J
        m = m.view(p, h, w, 2, 2, 2, 2).permute(0, 1, 3, 5, 2, 4, 6)
        return m.reshape(p, 4 * h, 4 * w)
