"""Blockwise autoregressive rollout of an action-conditioned world model (WPE, IRASim chaining).

A rollout starts from ``c`` context frames and a sequence of ``N`` actions. Each block takes the
last ``c`` frames, appends ``h`` noise frames, denoises them conditioned on the window's actions
(following the sampler's scheduling matrix), and slides by ``h``. IRASim's long-trajectory
chaining is ``c = 1, h = 15``. The whole rollout is one jitted function: ``lax.scan`` over blocks,
an inner ``lax.scan`` over sampling steps.

Action alignment follows the model: in a window of ``c + h`` frames, frame ``j >= 1`` is
conditioned on the action that led to it. For the first block the ``c - 1`` actions between the
context frames come from ``context_actions`` or, when they are not known, the null embedding.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from einops import rearrange

from wmjax.diffusion.sampling import sample_window
from wmjax.model import Params, WorldModel
from wmjax.nn.flops import forward_flops
from wmjax.parallel import mesh_context


def block_flops(world_model: WorldModel, batch: int, context: int, horizon: int, height: int,
                width: int) -> float:
  """Analytic network FLOPs of sampling one block of ``horizon`` frames after ``context`` frames:
  every model call runs the whole window, or, with ``sampler.kv_cache``, the context runs once and
  each call runs the new frames (their attention to the cached keys is left out). Guidance
  doubles everything."""
  net, copies = world_model.network, 2 if world_model.guided else 1
  calls = world_model.sampler.model_calls(horizon)
  if world_model.sampler.kv_cache:
    return copies * (forward_flops(net, batch, context, height, width)
                     + calls * forward_flops(net, batch, horizon, height, width))
  return copies * calls * forward_flops(net, batch, context + horizon, height, width)


# ----------------------------------------------------------------------------- validation


def _is_concrete(x) -> bool:
  return not isinstance(x, jax.core.Tracer)


def _check_finite(name: str, x) -> None:
  if _is_concrete(x) and not np.isfinite(np.asarray(x)).all():
    raise ValueError(f"{name} contain NaN or inf values")


def _check_array(name: str, x, ndim: int, layout: str) -> None:
  if getattr(x, "ndim", None) != ndim:
    raise ValueError(f"{name} must be {layout}, got shape {tuple(np.shape(x))}")


def check_rollout_inputs(world_model: WorldModel, context, actions, horizon: int,
                         context_actions=None) -> None:
  """ValueError, naming what was expected and what came, for any input the rollout cannot take."""
  net = world_model.network
  _check_array("context frames", context, 5, "[B, c, H, W, C]")
  _check_array("actions", actions, 3, "[B, N, A]")
  b, c = context.shape[:2]
  if actions.shape[0] != b:
    raise ValueError(f"batch sizes differ: context frames have B={b}, actions have "
                     f"B={actions.shape[0]}")
  if actions.shape[2] != net.action_dim:
    raise ValueError(f"actions must have dimension A={net.action_dim}, got {actions.shape[2]}")
  if actions.shape[1] < 1:
    raise ValueError("actions must hold at least one action, got N=0")
  if not isinstance(horizon, (int, np.integer)) or horizon < 1:
    raise ValueError(f"horizon must be a positive integer, got {horizon!r}")
  if c + horizon > net.num_frames:
    raise ValueError(f"context + horizon = {c} + {horizon} frames exceeds the {net.num_frames} "
                     f"frames the model supports")
  window = jax.ShapeDtypeStruct((b, c + horizon) + tuple(context.shape[2:]), jnp.float32)
  net.check_inputs(window, jax.ShapeDtypeStruct((b, c + horizon), jnp.float32),
                   jax.ShapeDtypeStruct((b, c + horizon - 1, net.action_dim), jnp.float32))
  if context_actions is not None:
    expected = (b, c - 1, net.action_dim)
    if tuple(context_actions.shape) != expected:
      raise ValueError(f"context_actions must be [B, c-1, A] = {expected}, got "
                       f"{tuple(context_actions.shape)}")
    _check_finite("context_actions", context_actions)
  _check_finite("context frames", context)
  _check_finite("actions", actions)


# ----------------------------------------------------------------------------- one block


def sample_block_traceable(world_model: WorldModel, params: Params, context: jax.Array,
                           window_actions: jax.Array, window_mask: jax.Array, rng: jax.Array
                           ) -> jax.Array:
  """:func:`sample_block` without its input checks, for callers that trace it inside their own
  ``jit`` / ``scan`` (closed-loop policy scans): the ``h`` frames ``[B, h, H, W, C]`` after
  ``context [B, c, H, W, C]`` under ``window_actions [B, c+h-1, A]`` and ``window_mask``."""
  c = context.shape[1]
  h = window_actions.shape[1] - c + 1
  noise_key, step_key = jax.random.split(rng)
  noise = jax.random.normal(noise_key, (context.shape[0], h) + context.shape[2:], jnp.float32)
  denoise = world_model.new_frame_denoiser(params, context.astype(jnp.float32), window_actions,
                                           window_mask)
  return sample_window(denoise, world_model.process, world_model.sampler, noise, step_key)


_sample_block_jit = jax.jit(sample_block_traceable, static_argnums=0)


def sample_block(world_model: WorldModel, params: Params, context: jax.Array,
                 window_actions: jax.Array, rng: jax.Array,
                 window_mask: jax.Array | None = None) -> jax.Array:
  """Generate the ``h`` frames that follow ``context [B, c, H, W, C]``: one jitted block.

  ``window_actions [B, c+h-1, A]`` are the actions of the window's frames 1..c+h-1 (the last
  ``h`` of them lead to the new frames); ``window_mask [B, c+h-1]`` marks the known ones (others
  use the null embedding). Returns ``[B, h, H, W, C]``. This is the step of closed-loop
  environments; :func:`rollout` scans it.
  """
  c = np.shape(context)[1] if np.ndim(context) == 5 else 0
  _check_array("window_actions", window_actions, 3, "[B, c+h-1, A]")
  horizon = window_actions.shape[1] - c + 1
  check_rollout_inputs(world_model, context, window_actions[:, c - 1:], horizon,
                       window_actions[:, :c - 1])
  if window_mask is None:
    window_mask = jnp.ones(window_actions.shape[:2], bool)
  elif tuple(window_mask.shape) != tuple(window_actions.shape[:2]):
    raise ValueError(f"window_mask must be [B, c+h-1] = {tuple(window_actions.shape[:2])}, got "
                     f"{tuple(window_mask.shape)}")
  with mesh_context(context):
    return _sample_block_jit(world_model, params, context, window_actions, window_mask, rng)


# ----------------------------------------------------------------------------- rollout


def block_key(rng: jax.Array, block: int | jax.Array) -> jax.Array:
  """The key block ``block`` of a rollout (or step ``block`` of an environment) samples with."""
  return jax.random.fold_in(rng, block)


def _rollout(world_model: WorldModel, params: Params, context: jax.Array, actions: jax.Array,
             action_mask: jax.Array, rng: jax.Array, horizon: int, num_frames: int) -> jax.Array:
  """``actions [B, c-1+K*h, A]`` cover the context and K whole blocks; returns ``[B, c+N, ...]``."""
  c, h = context.shape[1], horizon
  num_blocks = (actions.shape[1] - (c - 1)) // h
  index = np.arange(num_blocks)[:, None] * h + np.arange(c + h - 1)[None, :]  # [K, c+h-1]
  block_actions = jnp.moveaxis(actions[:, index], 1, 0)  # [K, B, c+h-1, A]
  block_mask = jnp.moveaxis(action_mask[:, index], 1, 0)
  keys = jax.vmap(block_key, (None, 0))(rng, jnp.arange(num_blocks))

  def body(ctx, block):
    window_actions, window_mask, key = block
    new = sample_block_traceable(world_model, params, ctx, window_actions, window_mask, key)
    return jnp.concatenate([ctx, new], axis=1)[:, -c:], new

  _, new_frames = jax.lax.scan(body, context.astype(jnp.float32),
                               (block_actions, block_mask, keys))
  new_frames = rearrange(new_frames, "k b h ... -> b (k h) ...")  # blocks in order
  return jnp.concatenate([context.astype(jnp.float32), new_frames], axis=1)[:, :num_frames]


_rollout_jit = jax.jit(_rollout, static_argnums=(0, 6, 7))


def rollout(world_model: WorldModel, params: Params, context: jax.Array, actions: jax.Array,
            rng: jax.Array, *, horizon: int, context_actions: jax.Array | None = None,
            action_mask: jax.Array | None = None) -> jax.Array:
  """Roll the model out from ``context [B, c, H, W, C]`` (the model's space: pixels in [-1, 1]
  or latents) under ``actions [B, N, A]``, *normalised* as the model was trained on them
  (``LoadedModel.action_stats.normalize(raw, config.data.normalization)``;
  :class:`wmjax.env.WorldModelEnv` takes raw actions and normalises them itself).

  ``actions[:, k]`` moves frame ``c-1+k`` to frame ``c+k``. Blocks of ``horizon`` frames are
  generated one after another; when N is not a multiple of ``horizon`` the last block is padded
  with null actions and its extra frames are dropped. Block ``k`` samples with
  :func:`block_key` ``(rng, k)``. ``context_actions [B, c-1, A]`` are the actions between the
  context frames, if known. ``action_mask [B, N]`` marks real actions: unmarked ones use the null
  embedding, so a batch of trajectories of different lengths padded to one N gives each the frames
  it would get alone (up to the sampling noise). Returns every frame, context included:
  ``[B, c+N, H, W, C]`` float32.
  """
  check_rollout_inputs(world_model, context, actions, horizon, context_actions)
  if action_mask is not None and tuple(np.shape(action_mask)) != tuple(actions.shape[:2]):
    raise ValueError(f"action_mask must be [B, N] = {tuple(actions.shape[:2])}, got "
                     f"{tuple(np.shape(action_mask))}")
  b, c = context.shape[:2]
  n, a = actions.shape[1:]
  num_blocks = math.ceil(n / horizon)
  pad = num_blocks * horizon - n
  if context_actions is None:
    context_actions = jnp.zeros((b, c - 1, a), jnp.float32)
    context_known = jnp.zeros((b, c - 1), bool)
  else:
    context_known = jnp.ones((b, c - 1), bool)
  all_actions = jnp.concatenate([jnp.asarray(context_actions, jnp.float32),
                                 jnp.asarray(actions, jnp.float32),
                                 jnp.zeros((b, pad, a), jnp.float32)], axis=1)
  known = jnp.ones((b, n), bool) if action_mask is None else jnp.asarray(action_mask, bool)
  mask = jnp.concatenate([context_known, known, jnp.zeros((b, pad), bool)], 1)
  with mesh_context(context):
    return _rollout_jit(world_model, params, jnp.asarray(context), all_actions, mask, rng,
                        horizon, c + n)
