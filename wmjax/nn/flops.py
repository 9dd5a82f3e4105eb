"""Analytic FLOPs of one ST-DiT forward pass (matmuls and attention, 2 FLOPs per multiply-add).

Elementwise work (norms, softmax, activations) is left out, as is usual for model FLOP
utilisation; on realistic widths it is a few percent of the total. Causal temporal attention is
counted in full, as XLA computes it.
"""

from __future__ import annotations

from wmjax.nn.dit import STDiT


def _matmul(m: int, k: int, n: int) -> int:
  return 2 * m * k * n


def _embedder(model: STDiT, rows: int, in_features: int) -> int:
  d, r = model.hidden_size, model.action_embed_ratio
  in_features *= 1 + 2 * model.action_fourier_features
  if r == 0:
    return _matmul(rows, in_features, d)
  return _matmul(rows, in_features, r * d) + _matmul(rows, r * d, d)


def forward_flops(model: STDiT, batch: int, frames: int, height: int, width: int) -> int:
  """FLOPs of ``model`` on ``[batch, frames, height, width, in_channels]`` (no guidance doubling)."""
  d, p, c = model.hidden_size, model.patch_size, model.in_channels
  patches = (height // p) * (width // p)
  frame_rows = batch * frames
  tokens = frame_rows * patches

  flops = _matmul(tokens, p * p * c, d)  # patch embedding
  flops += _matmul(frame_rows, 256, d) + _matmul(frame_rows, d, d)  # timestep embedder
  if model.cond in ("frame", "per_frame"):
    flops += _embedder(model, batch * (frames - 1), model.action_dim)
  if model.uses_trajectory:
    flops += _embedder(model, batch, (model.num_frames - 1) * model.action_dim)

  per_block = (_matmul(tokens, d, 3 * d) + _matmul(tokens, d, d)  # qkv, output projection
               + 2 * _matmul(tokens, d, model.mlp_ratio * d)  # MLP
               + _matmul(frame_rows, d, 6 * d))  # adaLN modulation
  num_layers = model.depth // 2
  flops += model.depth * per_block
  flops += num_layers * 2 * _matmul(frame_rows * patches, patches, d)  # spatial QK^T and AV
  flops += num_layers * 2 * _matmul(batch * patches * frames, frames, d)  # temporal QK^T and AV
  flops += _matmul(frame_rows, d, 2 * d) + _matmul(tokens, d, p * p * c)  # final layer
  return flops
