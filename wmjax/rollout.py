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

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from wmjax.diffusion import objectives
from wmjax.diffusion.sampling import (DenoiseFn, SamplerConfig, classifier_free_guidance,
                                      context_inputs, sample_window, window_denoiser)
from wmjax.nn.dit import STDiT
from wmjax.nn.flops import forward_flops
from wmjax.parallel import mesh_context

Params = Any


@dataclasses.dataclass(frozen=True, eq=False)
class WorldModel:
  """The network, its diffusion process and how it is sampled; hashable by identity (jit-static)."""

  network: STDiT
  process: objectives.Process
  sampler: SamplerConfig

  def __post_init__(self):
    if self.sampler.kv_cache and not self.network.causal_temporal:
      raise ValueError("sampling.kv_cache=True needs model.causal_temporal=True: with "
                       "bidirectional temporal attention the context frames attend to the new "
                       "frames, so their keys and values change at every sampling step")

  @classmethod
  def from_config(cls, config: ml_collections.ConfigDict) -> "WorldModel":
    """From a config with ``model`` (STDiT fields), ``diffusion`` and ``sampling`` sections."""
    d = config.diffusion
    process = objectives.make_process(d.kind, d.get("schedule", "linear"), d.num_timesteps,
                                      d.get("prediction", "eps"))
    sampler = SamplerConfig(**config.sampling.to_dict())
    if sampler.sampler not in process.samplers:
      raise ValueError(f"sampling.sampler={sampler.sampler!r} does not fit diffusion.kind="
                       f"{d.kind!r}; expected one of {process.samplers}")
    return cls(STDiT(**config.model.to_dict()), process, sampler)

  def init(self, rng: jax.Array, frame_shape: tuple[int, int, int], frames: int | None = None
           ) -> Params:
    """Initial variables for frames of ``frame_shape = (H, W, C)``."""
    n = frames or self.network.num_frames
    x = jnp.zeros((1, n) + tuple(frame_shape), jnp.float32)
    actions = jnp.zeros((1, n - 1, self.network.action_dim), jnp.float32)
    return self.network.init(rng, x, jnp.zeros((1, n), jnp.float32), actions)

  # Classifier-free guidance runs the network on the batch twice, conditional then null.

  @property
  def guided(self) -> bool:
    return self.sampler.guidance_scale != 1.0

  def _twice(self, x: jax.Array) -> jax.Array:
    return jnp.concatenate([x, x], axis=0) if self.guided else x

  def _conditioning(self, actions: jax.Array, action_mask: jax.Array):
    """``(actions, action_mask, drop_actions)`` of the network's batch."""
    if not self.guided:
      return actions, action_mask, None
    b = actions.shape[0]
    drop = jnp.concatenate([jnp.zeros((b,), bool), jnp.ones((b,), bool)])
    return self._twice(actions), self._twice(action_mask), drop

  def _guide(self, out: jax.Array) -> jax.Array:
    if not self.guided:
      return out
    b = out.shape[0] // 2
    return classifier_free_guidance(out[:b], out[b:], self.sampler.guidance_scale)

  def denoise(self, params: Params, x: jax.Array, levels: jax.Array, actions: jax.Array,
              action_mask: jax.Array) -> jax.Array:
    """Network output for the window ``x [B, T, ...]`` at process levels ``[B, T]``, with guidance."""
    t = self.process.model_time(levels)
    out = self.network.apply(params, self._twice(x), self._twice(t),
                             *self._conditioning(actions, action_mask))
    return self._guide(out)

  def new_frame_denoiser(self, params: Params, context: jax.Array, actions: jax.Array,
                         action_mask: jax.Array) -> DenoiseFn:
    """What the sampler calls at every step: ``(x [B, h, ...], levels [B, h]) -> out`` for the
    ``h`` frames after the clean ``context [B, c, ...]``, under the window's ``actions
    [B, c+h-1, A]`` and ``action_mask [B, c+h-1]``. With ``sampler.kv_cache`` the context goes
    through the network once, here; otherwise every step runs the whole window."""
    context_in, context_levels = context_inputs(self.process, self.sampler, context)
    if not self.sampler.kv_cache:
      return window_denoiser(lambda x, levels: self.denoise(params, x, levels, actions, action_mask),
                             context_in, context_levels)
    conditioning = self._conditioning(actions, action_mask)
    cache = self.network.apply(params, self._twice(context_in),
                               self._twice(self.process.model_time(context_levels)), *conditioning,
                               method="encode_context")

    def denoise(x, levels):
      out = self.network.apply(params, cache, self._twice(x),
                               self._twice(self.process.model_time(levels)), *conditioning,
                               method="extend")
      return self._guide(out)

    return denoise


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


def _sample_block(world_model: WorldModel, params: Params, context: jax.Array,
                  window_actions: jax.Array, window_mask: jax.Array, rng: jax.Array) -> jax.Array:
  c = context.shape[1]
  h = window_actions.shape[1] - c + 1
  noise_key, step_key = jax.random.split(rng)
  noise = jax.random.normal(noise_key, (context.shape[0], h) + context.shape[2:], jnp.float32)
  denoise = world_model.new_frame_denoiser(params, context.astype(jnp.float32), window_actions,
                                           window_mask)
  return sample_window(denoise, world_model.process, world_model.sampler, noise, step_key)


_sample_block_jit = jax.jit(_sample_block, static_argnums=0)


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
    new = _sample_block(world_model, params, ctx, window_actions, window_mask, key)
    return jnp.concatenate([ctx, new], axis=1)[:, -c:], new

  _, new_frames = jax.lax.scan(body, context.astype(jnp.float32),
                               (block_actions, block_mask, keys))
  new_frames = jnp.moveaxis(new_frames, 0, 1)  # [B, K, h, ...]
  new_frames = new_frames.reshape((new_frames.shape[0], num_blocks * h) + new_frames.shape[3:])
  return jnp.concatenate([context.astype(jnp.float32), new_frames], axis=1)[:, :num_frames]


_rollout_jit = jax.jit(_rollout, static_argnums=(0, 6, 7))


def rollout(world_model: WorldModel, params: Params, context: jax.Array, actions: jax.Array,
            rng: jax.Array, *, horizon: int, context_actions: jax.Array | None = None,
            action_mask: jax.Array | None = None) -> jax.Array:
  """Roll the model out from ``context [B, c, H, W, C]`` under ``actions [B, N, A]``.

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
