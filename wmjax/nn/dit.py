"""The spatial-temporal diffusion transformer (ST-DiT) of IRASim and WPE.

``STDiT(x, t, actions)`` maps a noisy window of frames ``x [B, T, H, W, C]`` (pixels or latents),
one model time per frame ``t [B, T]`` and the ``T-1`` actions between the frames
``actions [B, T-1, A]`` to the model output ``[B, T, H, W, C]`` (eps, v, x0 or flow velocity,
whatever the objective trains it to be).

Action alignment: ``actions[:, j]`` moves frame ``j`` to frame ``j+1``, so the conditioning vector
of frame ``j >= 1`` embeds ``actions[:, j-1]``; frame 0, every frame whose action is masked out
(``action_mask``) and every sample whose actions are dropped (``drop_actions``, action dropout in
training, the unconditional branch of classifier-free guidance) use one learned null embedding.

Conditioning modes (``cond``):

* ``frame``     IRASim Frame-Ada: spatial blocks and the final layer get
                ``temb(t_j) + aemb(a_{j-1})`` per frame; temporal blocks get ``temb(t_j)``
                (plus the trajectory embedding when ``trajectory_in_temporal``).
* ``video``     IRASim Video-Ada: one embedding of the whole flattened trajectory (zero-padded to
                ``num_frames - 1`` actions) is added to ``temb(t_j)`` for every block.
* ``per_frame`` WPE / Oasis: ``temb(t_j) + aemb(a_{j-1})`` in every block.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from wmjax.nn import layers
from wmjax.nn.layers import logical

COND_MODES = ("frame", "video", "per_frame")
# What a rematerialised layer keeps from its forward pass for the backward pass.
REMAT_POLICIES = {
    "none": None,  # no remat: keep every activation (fastest, most memory)
    "full": jax.checkpoint_policies.nothing_saveable,  # recompute the whole layer
    "dots": jax.checkpoint_policies.dots_with_no_batch_dims_saveable,  # keep weight matmuls
    "dots_all": jax.checkpoint_policies.dots_saveable,  # keep every matmul, attention's too
}
TEMPORAL_POSITIONS = ("sincos", "rope")


class LayerStack(nn.Module):
  """``num_layers`` spatial+temporal layers, scanned (stacked params, fast compiles) or unrolled."""

  num_layers: int
  num_heads: int
  mlp_ratio: int
  causal: bool
  rope: bool
  attention_impl: str | None
  dtype: jnp.dtype
  scan: bool
  remat: str

  @nn.compact
  def __call__(self, x, spatial_cond, temporal_cond):
    layer_cls = layers.STLayer
    if self.remat != "none":
      layer_cls = nn.remat(layer_cls, prevent_cse=not self.scan,
                           policy=REMAT_POLICIES[self.remat])
    kwargs = dict(num_heads=self.num_heads, mlp_ratio=self.mlp_ratio, causal=self.causal,
                  rope=self.rope, attention_impl=self.attention_impl, dtype=self.dtype)
    if self.scan:
      stack = nn.scan(layer_cls, variable_axes={"params": 0}, split_rngs={"params": True},
                      in_axes=(nn.broadcast, nn.broadcast), length=self.num_layers,
                      metadata_params={nn.PARTITION_NAME: "layers"})
      x, _ = stack(**kwargs, name="layers")(x, spatial_cond, temporal_cond)
      return x
    for i in range(self.num_layers):
      x, _ = layer_cls(**kwargs, name=f"layer_{i}")(x, spatial_cond, temporal_cond)
    return x


class STDiT(nn.Module):
  """Action-conditioned ST-DiT. See the module docstring for shapes and conditioning."""

  in_channels: int = 4
  patch_size: int = 2
  hidden_size: int = 1152
  depth: int = 28  # spatial + temporal blocks, so depth / 2 layers
  num_heads: int = 16
  mlp_ratio: int = 4
  num_frames: int = 16  # longest window the model accepts
  action_dim: int = 7
  cond: str = "frame"
  action_embed_ratio: int = 4  # 0: linear action embedding (WPE); r: MLP with hidden r*D (IRASim)
  trajectory_in_temporal: bool = False
  action_dropout: float = 0.1
  causal_temporal: bool = False
  temporal_pos: str = "sincos"
  attention_impl: str | None = None
  dtype: str = "float32"  # compute dtype; parameters are always float32
  scan_layers: bool = True
  remat: str = "none"  # a key of REMAT_POLICIES

  def setup(self):
    if self.cond not in COND_MODES:
      raise ValueError(f"cond must be one of {COND_MODES}, got {self.cond!r}")
    if self.temporal_pos not in TEMPORAL_POSITIONS:
      raise ValueError(f"temporal_pos must be one of {TEMPORAL_POSITIONS}, got {self.temporal_pos!r}")
    if self.remat not in REMAT_POLICIES:
      raise ValueError(f"remat must be one of {sorted(REMAT_POLICIES)}, got {self.remat!r}")
    if self.depth % 2:
      raise ValueError(f"depth counts spatial + temporal blocks and must be even, got {self.depth}")
    if self.hidden_size % self.num_heads:
      raise ValueError(f"hidden_size {self.hidden_size} is not divisible by num_heads {self.num_heads}")
    dtype = jnp.dtype(self.dtype)
    d = self.hidden_size
    self.patch_embed = layers.PatchEmbed(self.patch_size, d, dtype=dtype)
    self.time_embed = layers.TimestepEmbedder(d, dtype=dtype)
    if self.cond in ("frame", "per_frame"):
      self.action_embed = layers.ActionEmbedder(d, self.action_embed_ratio, dtype=dtype)
    if self.uses_trajectory:
      self.trajectory_embed = layers.ActionEmbedder(d, self.action_embed_ratio, dtype=dtype)
    self.null_action = self.param("null_action", logical(nn.initializers.normal(0.02), "embed"),
                                  (d,))
    self.blocks = LayerStack(self.depth // 2, self.num_heads, self.mlp_ratio, self.causal_temporal,
                             self.temporal_pos == "rope", self.attention_impl, dtype,
                             self.scan_layers, self.remat)
    self.final_layer = layers.FinalLayer(self.patch_size ** 2 * self.in_channels, dtype=dtype)

  @property
  def uses_trajectory(self) -> bool:
    return self.cond == "video" or (self.cond == "frame" and self.trajectory_in_temporal)

  # ------------------------------------------------------------------------- validation

  def check_inputs(self, x, t, actions, action_mask=None, drop_actions=None) -> None:
    """Raise ValueError naming what was expected and what came; shapes only (jit-safe)."""
    if x.ndim != 5:
      raise ValueError(f"frames must be [B, T, H, W, C], got shape {tuple(x.shape)}")
    b, n, h, w, c = x.shape
    p = self.patch_size
    if c != self.in_channels:
      raise ValueError(f"frames must have {self.in_channels} channels, got {c} (shape {x.shape})")
    if h % p or w % p:
      raise ValueError(f"frame size must be divisible by the patch size {p}, got {h}x{w}")
    if n > self.num_frames:
      raise ValueError(f"the model supports at most {self.num_frames} frames, got {n}")
    if tuple(t.shape) != (b, n):
      raise ValueError(f"noise levels must be [B, T] = {(b, n)}, got {tuple(t.shape)}")
    if tuple(actions.shape) != (b, n - 1, self.action_dim):
      raise ValueError(
          f"actions must be [B, T-1, A] = {(b, n - 1, self.action_dim)} for {n} frames, "
          f"got {tuple(actions.shape)}")
    if action_mask is not None and tuple(action_mask.shape) != (b, n - 1):
      raise ValueError(f"action_mask must be [B, T-1] = {(b, n - 1)}, got {tuple(action_mask.shape)}")
    if drop_actions is not None and tuple(drop_actions.shape) != (b,):
      raise ValueError(f"drop_actions must be [B] = {(b,)}, got {tuple(drop_actions.shape)}")

  # ------------------------------------------------------------------------- conditioning

  def conditioning(self, t, actions, action_mask=None, drop_actions=None):
    """Per-frame conditioning vectors for the spatial blocks, temporal blocks and final layer.

    ``t [B, T]``, ``actions [B, T-1, A]``, ``action_mask [B, T-1]`` (False -> null embedding),
    ``drop_actions [B]`` (True -> every frame of the sample uses the null embedding).
    Returns three ``[B, T, D]`` arrays.
    """
    b, n = t.shape
    dtype = jnp.dtype(self.dtype)
    temb = self.time_embed(t)  # [B, T, D]
    null = self.null_action.astype(dtype)
    drop = jnp.zeros((b,), bool) if drop_actions is None else drop_actions
    if action_mask is None:
      action_mask = jnp.ones((b, n - 1), bool)

    frame_emb = None
    if self.cond in ("frame", "per_frame"):
      emb = self.action_embed(actions.astype(dtype))  # [B, T-1, D]
      keep = action_mask & ~drop[:, None]
      emb = jnp.where(keep[..., None], emb, null)
      frame_emb = jnp.concatenate([jnp.broadcast_to(null, (b, 1, emb.shape[-1])), emb], axis=1)

    traj_emb = None
    if self.uses_trajectory:
      padded = jnp.where(action_mask[..., None], actions, 0.0)
      padded = jnp.pad(padded, ((0, 0), (0, self.num_frames - n), (0, 0)))
      traj_emb = self.trajectory_embed(padded.reshape(b, -1).astype(dtype))  # [B, D]
      traj_emb = jnp.where(drop[:, None], null, traj_emb)[:, None, :]

    if self.cond == "video":
      c = temb + traj_emb
      return c, c, c
    spatial = temb + frame_emb
    if self.cond == "per_frame":
      return spatial, spatial, spatial
    temporal = temb + traj_emb if traj_emb is not None else temb
    return spatial, temporal, spatial

  # ------------------------------------------------------------------------- forward

  def __call__(self, x, t, actions, action_mask=None, drop_actions=None, *, train: bool = False):
    """``x [B, T, H, W, C]``, ``t [B, T]``, ``actions [B, T-1, A]`` -> ``[B, T, H, W, C]`` float32.

    With ``train=True`` and ``action_dropout > 0`` a ``'dropout'`` RNG drops the actions of each
    sample with that probability.
    """
    self.check_inputs(x, t, actions, action_mask, drop_actions)
    b, n, h, w, _ = x.shape
    dtype = jnp.dtype(self.dtype)
    if train and self.action_dropout > 0:
      dropped = jax.random.bernoulli(self.make_rng("dropout"), self.action_dropout, (b,))
      drop_actions = dropped if drop_actions is None else drop_actions | dropped
    spatial_cond, temporal_cond, final_cond = self.conditioning(t, actions, action_mask,
                                                                drop_actions)

    gh, gw = h // self.patch_size, w // self.patch_size
    tokens = self.patch_embed(x.astype(dtype))  # [B, T, P, D]
    pos = layers.sincos_2d(self.hidden_size, gh, gw)[None, None]
    if self.temporal_pos == "sincos":
      pos = pos + layers.sincos_1d(self.hidden_size, np.arange(n))[None, :, None]
    tokens = tokens + pos.astype(dtype)

    tokens = self.blocks(tokens, spatial_cond, temporal_cond)
    out = self.final_layer(tokens, final_cond)  # [B, T, P, p*p*C]
    return layers.unpatchify(out, gh, gw, self.patch_size).astype(jnp.float32)
