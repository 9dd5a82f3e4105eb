"""The spatial-temporal diffusion transformer (ST-DiT) of IRASim and WPE.

``STDiT(x, t, actions)`` maps a noisy window of frames ``x [B, T, H, W, C]`` (pixels or latents),
one model time per frame ``t [B, T]`` and the ``T-1`` actions between the frames
``actions [B, T-1, A]`` to the model output ``[B, T, H, W, C]`` (eps, v, x0 or flow velocity,
whatever the objective trains it to be).

Several cameras (``views = V > 1``): a frame holds the V views of one time step side by side,
``W = V * Wv`` (as :class:`wmjax.data.oxe.DatasetSpec` tiles several ``image_keys``), each view a
multiple of the patch size wide. Every view's patches get the same 2-D positions (sin-cos and
axial RoPE over the view's own grid) plus a learned view embedding, and one spatial attention
runs over the tokens of all views of a time step; temporal attention stays per token, and the
views of a step share its action and noise level. ``views = 1`` on the same frames is the tiled
baseline: positions over the whole ``H x W`` canvas and no view embedding, at the same FLOPs.

Action alignment: ``actions[:, j]`` moves frame ``j`` to frame ``j+1``, so the conditioning vector
of frame ``j >= 1`` embeds ``actions[:, j-1]``; frame 0, every frame whose action is masked out
(``action_mask``) and every sample whose actions are dropped (``drop_actions``, action dropout in
training, the unconditional branch of classifier-free guidance) use one learned null embedding.

Conditioning modes (``cond``):

* ``frame``     IRASim Frame-Ada: spatial blocks and the final layer (``temb(t_j)`` alone with
                ``final_layer_actions=False``) get ``temb(t_j) + aemb(a_{j-1})`` per frame;
                temporal blocks get ``temb(t_j)``
                (plus the trajectory embedding when ``trajectory_in_temporal``).
* ``video``     IRASim Video-Ada: one embedding of the whole flattened trajectory (zero-padded to
                ``num_frames - 1`` actions) is added to ``temb(t_j)`` for every block.
* ``per_frame`` WPE / Oasis: ``temb(t_j) + aemb(a_{j-1})`` in every block.

Temporal KV cache (rollouts): with causal temporal attention the first ``c`` frames of a window
never see the later ones, so their activations do not depend on the frames being denoised.
:meth:`STDiT.encode_context` runs them once and keeps every layer's temporal keys and values;
:meth:`STDiT.extend` then runs only the window's last ``n - c`` frames against that cache and
gives what :meth:`STDiT.__call__` gives for them on the whole window.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from wmjax.nn import attention, float8, layers, text_actions
from wmjax.nn.layers import logical

COND_MODES = ("frame", "video", "per_frame")
# How an action reaches its embedding: "raw" numbers (ActionEmbedder), or "text", written as digit
# tokens and read by a small Transformer (wmjax.nn.text_actions; frame / per_frame cond only).
ACTION_ENCODINGS = ("raw", "text")
# What a rematerialised layer keeps from its forward pass for the backward pass. Besides XLA's
# own classes of values, the blocks name three (wmjax.nn.layers, jax.ad_checkpoint.checkpoint_name):
# "attention" (the attention's output before its projection, [tokens, D]), "normed" (each
# block's layer-normed and adaLN-modulated input to attention and to the MLP, [tokens, D] each)
# and "mlp_activation" (the GELU output, [tokens, 4D]).
_WEIGHT_MATMULS = jax.checkpoint_policies.dots_with_no_batch_dims_saveable
REMAT_POLICIES = {
    "none": None,  # no remat: keep every activation (fastest, most memory)
    # weight matmuls, attention outputs and every matmul's normalised / activated input: only
    # the residual adds, gates and the attention's inner softmax are recomputed
    "dots_elementwise": jax.checkpoint_policies.save_from_both_policies(
        _WEIGHT_MATMULS, jax.checkpoint_policies.save_only_these_names(
            "attention", "normed", "mlp_activation")),
    # weight matmuls and attention outputs: the attention is not recomputed, the elementwise work
    # (layer norms, modulation, GELU) is
    "dots_attention": jax.checkpoint_policies.save_from_both_policies(
        _WEIGHT_MATMULS, jax.checkpoint_policies.save_only_these_names("attention")),
    "dots": _WEIGHT_MATMULS,  # keep weight matmuls: attention and elementwise work recomputed
    "dots_all": jax.checkpoint_policies.dots_saveable,  # keep every matmul, attention's too
    "full": jax.checkpoint_policies.nothing_saveable,  # recompute the whole layer
}
# How a token knows where it is: "sincos" adds fixed sin-cos embeddings to the tokens; "rope"
# rotates queries and keys (1-D over frames, axial 2-D over the patch grid), so attention scores
# depend on relative offsets; "sincos+rope" does both, for actions that name absolute positions
# (a target in the image) while moves are relative offsets.
POSITIONS = ("sincos", "rope", "sincos+rope")
# Where the temporal sin-cos embedding joins the tokens: "input", with the spatial one, before the
# first block; "first_temporal", right before the first temporal block (IRASim's code, where a
# spatial-first stack's first spatial block sees no frame index).
TEMPORAL_SINCOS_AT = ("input", "first_temporal")


class LayerStack(nn.Module):
  """``num_layers`` spatial+temporal layers, scanned (stacked params, fast compiles) or unrolled.

  ``x [B, T, P, D]``, ``patch_positions [P, 2]`` -> ``(x', kv)``. ``cache`` holds every layer's
  temporal keys and values of ``Tc`` earlier frames (``[layers, B*P, Tc, H, d]`` each); with
  ``return_kv`` ``kv`` is the same for ``x``'s frames, else None. ``frame_pos [1, T, 1, D]`` (or
  None) is added to the tokens right before the first layer's temporal block.
  """

  num_layers: int
  num_heads: int
  mlp_ratio: int
  causal: bool
  rope: bool
  attention_impl: str | None
  dtype: jnp.dtype
  scan: bool
  remat: str
  temporal_first: bool = False
  spatial_rope: bool = False
  fp8: bool = False

  @nn.compact
  def __call__(self, x, spatial_cond, temporal_cond, patch_positions, cache=None,
               return_kv: bool = False, frame_pos=None):
    layer_cls = layers.STLayer
    if self.remat != "none":
      layer_cls = nn.remat(layer_cls, prevent_cse=not self.scan,
                           policy=REMAT_POLICIES[self.remat])
    kwargs = dict(num_heads=self.num_heads, mlp_ratio=self.mlp_ratio, causal=self.causal,
                  rope=self.rope, attention_impl=self.attention_impl, dtype=self.dtype,
                  return_kv=return_kv, temporal_first=self.temporal_first,
                  spatial_rope=self.spatial_rope, fp8=self.fp8)
    inputs = (x, spatial_cond, temporal_cond, patch_positions)
    if self.scan:
      # the scanned layers take frame_pos per layer: as given for the first, zeros for the others
      layer_pos = None if frame_pos is None else (
          jnp.zeros((self.num_layers,) + frame_pos.shape, frame_pos.dtype).at[0].set(frame_pos))
      stack = nn.scan(layer_cls, variable_axes={"params": 0, float8.COLLECTION: 0},
                      split_rngs={"params": True},
                      in_axes=(nn.broadcast,) * 3 + (0, 0), length=self.num_layers,
                      metadata_params={nn.PARTITION_NAME: "layers"})
      return stack(**kwargs, name="layers")(*inputs, cache, layer_pos)
    kvs = []
    for i in range(self.num_layers):
      layer_cache = None if cache is None else jax.tree.map(lambda a: a[i], cache)
      x, kv = layer_cls(**kwargs, name=f"layer_{i}")(x, *inputs[1:], layer_cache,
                                                     frame_pos if i == 0 else None)
      kvs.append(kv)
    return x, (jax.tree.map(lambda *a: jnp.stack(a), *kvs) if return_kv else None)


def _abstract_like(leaf: jax.ShapeDtypeStruct, shape: tuple, spec) -> jax.ShapeDtypeStruct:
  """``leaf`` with ``shape``; a named sharding's partition spec becomes ``spec(old spec)``."""
  sharding = leaf.sharding
  if isinstance(sharding, jax.sharding.NamedSharding):
    sharding = jax.sharding.NamedSharding(sharding.mesh,
                                          jax.sharding.PartitionSpec(*spec(tuple(sharding.spec))))
  return jax.ShapeDtypeStruct(shape, leaf.dtype, sharding=sharding)


def _stacked(leaves: list):
  """One leaf with a new leading axis over ``leaves`` (arrays, or ShapeDtypeStructs whose
  sharding gains an unsharded leading axis)."""
  first = leaves[0]
  if isinstance(first, jax.ShapeDtypeStruct):
    return _abstract_like(first, (len(leaves),) + tuple(first.shape), lambda s: (None,) + s)
  return jnp.stack(leaves)


def _layer(leaf, i: int):
  """Layer ``i`` of a stacked leaf (its leading axis dropped)."""
  if isinstance(leaf, jax.ShapeDtypeStruct):
    return _abstract_like(leaf, tuple(leaf.shape[1:]), lambda s: s[1:])
  return leaf[i]


def _stack_layers(blocks: Mapping, scan: bool) -> dict:
  """A :class:`LayerStack`'s variables ``{'layers': stacked}`` or ``{'layer_i': ...}`` laid out
  as ``scan`` asks."""
  unrolled = sorted((k for k in blocks if k.startswith("layer_")), key=lambda k: int(k[6:]))
  if scan and unrolled:
    if "layers" in blocks or unrolled != [f"layer_{i}" for i in range(len(unrolled))]:
      raise ValueError(f"cannot stack layers {unrolled} beside {sorted(blocks)}: expected "
                       f"layer_0 .. layer_{{n-1}} and nothing else")
    return {"layers": jax.tree.map(lambda *a: _stacked(list(a)), *(blocks[k] for k in unrolled))}
  if not scan and "layers" in blocks:
    stacked = blocks["layers"]
    count = {leaf.shape[0] for leaf in jax.tree.leaves(stacked)}
    if len(count) != 1 or len(blocks) != 1:
      raise ValueError(f"cannot unstack {sorted(blocks)}: expected one 'layers' entry whose "
                       f"arrays share a leading axis, got leading axes {sorted(count)}")
    return {f"layer_{i}": jax.tree.map(lambda a, i=i: _layer(a, i), stacked)
            for i in range(count.pop())}
  return dict(blocks)


def relayout_layers(tree, scan: bool):
  """``tree`` with the layers of every ST-DiT in it laid out as ``model.scan_layers=scan``
  keeps them: stacked along a leading axis under ``blocks/layers`` (scanned) or one
  ``blocks/layer_i`` each (unrolled). The two layouts compute the same function, so a checkpoint
  trained with one runs (and trains on) with the other. ``tree``: parameters, an optimiser
  state or a whole train state (any pytree whose dicts mirror the parameters), of arrays or of
  ``jax.ShapeDtypeStruct``s (a stacked one's sharding gains an unsharded leading axis); a tree
  laid out so already comes back with the same leaves."""
  if isinstance(tree, Mapping):
    out = {k: relayout_layers(v, scan) for k, v in tree.items()}
    if isinstance(out.get("blocks"), Mapping):
      out["blocks"] = _stack_layers(out["blocks"], scan)
    return out if isinstance(tree, dict) else type(tree)(out)
  children, treedef = jax.tree_util.tree_flatten(tree, is_leaf=lambda x: x is not tree)
  if treedef.num_leaves == 1 and treedef.num_nodes == 1:  # a leaf
    return tree
  return treedef.unflatten([relayout_layers(c, scan) for c in children])


def layers_scanned(paths: Iterable[str]) -> bool | None:
  """Whether the ST-DiT layers named by ``paths`` (``'params/blocks/layers/...'``, as
  :func:`wmjax.train.checkpoint.shapes_by_path` names a tree's arrays) are stacked (True) or
  unrolled (False); None when none is named."""
  paths = list(paths)
  if any("blocks/layers/" in p for p in paths):
    return True
  if any("blocks/layer_" in p for p in paths):
    return False
  return None


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
  action_fourier_features: int = 0  # K > 0: sin / cos of 2^k pi a (k < K) beside each raw action
  action_encoding: str = "raw"  # a key of ACTION_ENCODINGS
  # (x, y): the indexes of two action numbers that name a place in the image (a target position;
  # x along the columns, y down the rows). Each frame's tokens then get layers.PlaceEmbedder's
  # embedding of where its incoming action points, seen from each patch. () : none.
  action_place: tuple[int, ...] = ()
  trajectory_in_temporal: bool = False
  # camera views side by side in each frame (module docstring); 1: one image, or views tiled
  views: int = 1
  action_dropout: float = 0.1
  causal_temporal: bool = False
  temporal_first: bool = False  # each layer: temporal block, then spatial (default spatial first)
  temporal_pos: str = "sincos"  # a key of POSITIONS, across frames
  spatial_pos: str = "sincos"  # a key of POSITIONS, over the patch grid
  # where the temporal sin-cos embedding is added: a key of TEMPORAL_SINCOS_AT
  temporal_sincos_at: str = "input"
  spatial_sincos_columns_first: bool = False  # the column in the first half (IRASim's code)
  # cond='frame': the final layer is conditioned on the action embedding too (False: on the
  # timestep only, as IRASim's published Frame-Ada checkpoints were trained, final_frame_ada=False)
  final_layer_actions: bool = True
  attention_impl: str | None = "xla"  # a backend of wmjax.nn.attention (None: xla)
  dtype: str = "float32"  # compute dtype; parameters are always float32
  scan_layers: bool = True
  remat: str = "none"  # a key of REMAT_POLICIES
  # the linear layers of the blocks (attention projections, MLPs) in float8 e4m3, for inference:
  # twice the matmul peak on Ada / Hopper / Blackwell GPUs (wmjax.nn.float8); training refuses it
  fp8_matmuls: bool = False

  def setup(self):
    if self.cond not in COND_MODES:
      raise ValueError(f"cond must be one of {COND_MODES}, got {self.cond!r}")
    for field in ("temporal_pos", "spatial_pos"):
      if getattr(self, field) not in POSITIONS:
        raise ValueError(f"{field} must be one of {POSITIONS}, got {getattr(self, field)!r}")
    if self.temporal_sincos_at not in TEMPORAL_SINCOS_AT:
      raise ValueError(f"temporal_sincos_at must be one of {TEMPORAL_SINCOS_AT}, got "
                       f"{self.temporal_sincos_at!r}")
    if self.action_encoding not in ACTION_ENCODINGS:
      raise ValueError(f"action_encoding must be one of {ACTION_ENCODINGS}, got "
                       f"{self.action_encoding!r}")
    if self.action_encoding == "text" and self.cond not in ("frame", "per_frame"):
      raise ValueError(f"action_encoding='text' embeds one action per frame, so cond must be "
                       f"'frame' or 'per_frame', got {self.cond!r}")
    if self.action_fourier_features < 0:
      raise ValueError(f"action_fourier_features must be >= 0, got {self.action_fourier_features}")
    place = tuple(self.action_place)
    if place and (len(place) != 2 or len(set(place)) != 2
                  or not all(0 <= i < self.action_dim for i in place)):
      raise ValueError(f"action_place must be () or two different action indexes (x, y) below "
                       f"action_dim={self.action_dim}, got {self.action_place!r}")
    if self.views < 1:
      raise ValueError(f"views must be >= 1, got {self.views}")
    if place and self.views > 1:
      raise ValueError(f"action_place names a place in one image; it is not defined for "
                       f"views={self.views}")
    if place and self.cond not in ("frame", "per_frame"):
      raise ValueError(f"action_place places each frame's incoming action, so cond must be "
                       f"'frame' or 'per_frame', got {self.cond!r}")
    if self.remat not in REMAT_POLICIES:
      raise ValueError(f"remat must be one of {sorted(REMAT_POLICIES)}, got {self.remat!r}")
    if self.depth % 2:
      raise ValueError(f"depth counts spatial + temporal blocks and must be even, got {self.depth}")
    if self.hidden_size % self.num_heads:
      raise ValueError(f"hidden_size {self.hidden_size} is not divisible by num_heads {self.num_heads}")
    dtype = jnp.dtype(self.dtype)
    attention.check_backend(self.attention_impl, dtype)
    d = self.hidden_size
    self.patch_embed = layers.PatchEmbed(self.patch_size, d, dtype=dtype)
    self.time_embed = layers.TimestepEmbedder(d, dtype=dtype)
    if self.cond in ("frame", "per_frame"):
      self.action_embed = (
          text_actions.TextActionEmbedder(d, dtype=dtype) if self.action_encoding == "text" else
          layers.ActionEmbedder(d, self.action_embed_ratio, self.action_fourier_features,
                                dtype=dtype))
    if self.uses_trajectory:
      self.trajectory_embed = layers.ActionEmbedder(d, self.action_embed_ratio,
                                                    self.action_fourier_features, dtype=dtype)
    if self.action_place:
      self.place_embed = layers.PlaceEmbedder(d, dtype=dtype)
    if self.views > 1:
      self.view_embed = self.param("view_embed", logical(nn.initializers.normal(0.02), None,
                                                         "embed"), (self.views, d))
    self.null_action = self.param("null_action", logical(nn.initializers.normal(0.02), "embed"),
                                  (d,))
    self.blocks = LayerStack(self.depth // 2, self.num_heads, self.mlp_ratio, self.causal_temporal,
                             "rope" in self.temporal_pos, self.attention_impl, dtype,
                             self.scan_layers, self.remat, self.temporal_first,
                             "rope" in self.spatial_pos, self.fp8_matmuls)
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
    if w % (p * self.views):
      raise ValueError(f"the frame's width must hold {self.views} views of whole {p}-pixel "
                       f"patches, got {h}x{w}")
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

  def check_frames(self, x, t, actions, first: int, action_mask=None, drop_actions=None) -> None:
    """Like :meth:`check_inputs` for frames ``first .. first+m-1`` (``x [B, m, H, W, C]``,
    ``t [B, m]``) of a window of ``n = actions.shape[1] + 1`` frames."""
    if x.ndim != 5 or actions.ndim != 3:
      raise ValueError(f"frames must be [B, m, H, W, C] and actions [B, n-1, A], got shapes "
                       f"{tuple(x.shape)} and {tuple(actions.shape)}")
    b, m = x.shape[:2]
    n = actions.shape[1] + 1
    if not 0 < first + m <= n:
      raise ValueError(f"frames {first}..{first + m - 1} do not lie in the window of {n} frames "
                       f"that {n - 1} actions describe")
    if tuple(t.shape) != (b, m):
      raise ValueError(f"noise levels must be [B, m] = {(b, m)}, got {tuple(t.shape)}")
    self.check_inputs(jax.ShapeDtypeStruct((b, n) + tuple(x.shape[2:]), x.dtype),
                      jax.ShapeDtypeStruct((b, n), t.dtype), actions, action_mask, drop_actions)

  @staticmethod
  def _frame_keeps(actions, action_mask, drop_actions, first: int, m: int) -> jax.Array:
    """``[B, m]``: whether frames ``first .. first+m-1`` of the window that ``actions [B, n-1,
    A]`` describe are conditioned on their incoming action (False for frame 0, masked actions
    and every frame of a dropped sample)."""
    keep = jnp.ones(actions.shape[:2], bool) if action_mask is None else action_mask
    if drop_actions is not None:
      keep = keep & ~drop_actions[:, None]
    keep = jnp.concatenate([jnp.zeros((actions.shape[0], 1), bool), keep], axis=1)
    return keep[:, first:first + m]

  def conditioning(self, t, actions, action_mask=None, drop_actions=None, first: int = 0):
    """Per-frame conditioning vectors for the spatial blocks, temporal blocks and final layer.

    ``t [B, m]`` are the model times of frames ``first .. first+m-1`` of a window of
    ``n = actions.shape[1] + 1`` frames; ``actions [B, n-1, A]``, ``action_mask [B, n-1]`` (False
    -> null embedding), ``drop_actions [B]`` (True -> every frame of the sample uses the null
    embedding). Returns three ``[B, m, D]`` arrays.
    """
    b, m = t.shape
    n = actions.shape[1] + 1
    dtype = jnp.dtype(self.dtype)
    temb = self.time_embed(t)  # [B, m, D]
    null = self.null_action.astype(dtype)
    drop = jnp.zeros((b,), bool) if drop_actions is None else drop_actions
    if action_mask is None:
      action_mask = jnp.ones((b, n - 1), bool)

    frame_emb = None
    if self.cond in ("frame", "per_frame"):
      # written this way, not with _frame_keeps on the frames: XLA rounds that program
      # differently, and trained models (the README quickstart's) would change
      emb = self.action_embed(actions.astype(dtype))  # [B, n-1, D]
      keep = action_mask & ~drop[:, None]
      emb = jnp.where(keep[..., None], emb, null)
      frame_emb = jnp.concatenate([jnp.broadcast_to(null, (b, 1, emb.shape[-1])), emb], axis=1)
      frame_emb = frame_emb[:, first:first + m]

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
    return spatial, temporal, spatial if self.final_layer_actions else temb

  # ------------------------------------------------------------------------- forward

  def __call__(self, x, t, actions, action_mask=None, drop_actions=None, *, train: bool = False):
    """``x [B, T, H, W, C]``, ``t [B, T]``, ``actions [B, T-1, A]`` -> ``[B, T, H, W, C]`` float32.

    With ``train=True`` and ``action_dropout > 0`` a ``'dropout'`` RNG drops the actions of each
    sample with that probability.
    """
    self.check_inputs(x, t, actions, action_mask, drop_actions)
    if train and self.action_dropout > 0:
      dropped = jax.random.bernoulli(self.make_rng("dropout"), self.action_dropout, (x.shape[0],))
      drop_actions = dropped if drop_actions is None else drop_actions | dropped
    out, _ = self._forward(x, t, actions, action_mask, drop_actions)
    return out

  def encode_context(self, context, t, actions, action_mask=None, drop_actions=None):
    """The temporal KV cache of a window's first ``c`` frames, for :meth:`extend`.

    ``context [B, c, H, W, C]`` and their model times ``t [B, c]``; ``actions [B, n-1, A]`` (and
    ``action_mask``, ``drop_actions``) are those of the whole ``n``-frame window, ``c < n``.
    Returns ``(keys, values)``, each ``[layers, B*P, c, heads, head_dim]`` in the compute dtype.
    Needs ``causal_temporal``: otherwise the context frames attend to the later ones.
    """
    if not self.causal_temporal:
      raise ValueError("a temporal KV cache needs model.causal_temporal=True: with bidirectional "
                       "temporal attention the context frames attend to the frames after them")
    self.check_frames(context, t, actions, 0, action_mask, drop_actions)
    if context.shape[1] >= actions.shape[1] + 1:
      raise ValueError(f"the context ({context.shape[1]} frames) must leave frames to generate in "
                       f"the window of {actions.shape[1] + 1}")
    _, cache = self._forward(context, t, actions, action_mask, drop_actions, return_kv=True)
    return cache

  def extend(self, cache, x, t, actions, action_mask=None, drop_actions=None):
    """Output for the last ``h`` frames of a window whose first ``c`` are in ``cache``.

    ``cache`` from :meth:`encode_context` with the same actions, ``x [B, h, H, W, C]``,
    ``t [B, h]``, ``actions [B, c+h-1, A]`` -> ``[B, h, H, W, C]`` float32: what :meth:`__call__`
    gives for these frames on the whole window.
    """
    first = cache[0].shape[2]
    if x.shape[1] + first != actions.shape[1] + 1:
      raise ValueError(f"a cache of {first} frames and {x.shape[1]} new frames make "
                       f"{first + x.shape[1]}, but the actions describe a window of "
                       f"{actions.shape[1] + 1}")
    self.check_frames(x, t, actions, first, action_mask, drop_actions)
    b, _, h, w, _ = x.shape
    expected = (self.depth // 2, b * (h // self.patch_size) * (w // self.patch_size), first,
                self.num_heads, self.hidden_size // self.num_heads)
    if any(tuple(a.shape) != expected for a in cache):
      raise ValueError(f"cache keys and values must be [layers, B*P, c, heads, head_dim] = "
                       f"{expected}, got {[tuple(a.shape) for a in cache]}")
    out, _ = self._forward(x, t, actions, action_mask, drop_actions, first=first, cache=cache)
    return out

  def _forward(self, x, t, actions, action_mask, drop_actions, first: int = 0, cache=None,
               return_kv: bool = False):
    """Frames ``first ..`` of the window -> (output or None when ``return_kv``, kv or None)."""
    b, m, h, w, _ = x.shape
    dtype = jnp.dtype(self.dtype)
    spatial_cond, temporal_cond, final_cond = self.conditioning(t, actions, action_mask,
                                                                drop_actions, first)
    gh, gw = h // self.patch_size, w // self.patch_size
    tokens = self.patch_embed(x.astype(dtype))  # [B, m, P, D], row-major over the whole frame
    rows, cols = np.meshgrid(np.arange(gh), np.arange(gw), indexing="ij")
    view_width = gw // self.views
    view, cols = cols.reshape(-1) // view_width, cols.reshape(-1) % view_width  # [P] each
    pos = np.zeros((1, 1, 1, self.hidden_size))
    if "sincos" in self.spatial_pos:
      grid = layers.sincos_2d(self.hidden_size, gh, view_width,
                              self.spatial_sincos_columns_first)
      pos = pos + grid[rows.reshape(-1) * view_width + cols][None, None]
    frame_pos = None
    if "sincos" in self.temporal_pos:
      frame_pos = layers.sincos_1d(self.hidden_size, np.arange(first, first + m))[None, :, None]
      if self.temporal_sincos_at == "input":
        pos, frame_pos = pos + frame_pos, None
    tokens = tokens + pos.astype(dtype)
    if self.views > 1:
      tokens = tokens + self.view_embed.astype(dtype)[view]
    if self.action_place:  # frame j's incoming action a_{j-1}; frame 0's (zeros) is not kept
      incoming = jnp.pad(actions, ((0, 0), (1, 0), (0, 0)))[:, first:first + m]
      place = self.place_embed(incoming[..., list(self.action_place)], gh, gw)  # [B, m, P, D]
      keep = self._frame_keeps(actions, action_mask, drop_actions, first, m)
      tokens = tokens + jnp.where(keep[:, :, None, None], place, 0).astype(dtype)
    patch_positions = jnp.asarray(np.stack([rows.reshape(-1), cols], axis=1))

    tokens, kv = self.blocks(tokens, spatial_cond, temporal_cond, patch_positions, cache,
                             return_kv, None if frame_pos is None else frame_pos.astype(dtype))
    if return_kv:
      return None, kv
    out = self.final_layer(tokens, final_cond)  # [B, m, P, p*p*C]
    return layers.unpatchify(out, gh, gw, self.patch_size).astype(jnp.float32), None
