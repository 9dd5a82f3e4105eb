"""Samplers with per-frame noise levels, scheduling matrices and classifier-free guidance.

A sampling run over a window of ``h`` new frames follows a *scheduling matrix* (diffusion
forcing): row ``i`` gives, for every new frame, an index into the process's sampling levels
(``S`` = pure noise, ``0`` = clean). Each row-to-row transition is one network call and one
sampler step; frames whose level does not change keep their values.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from wmjax.diffusion.objectives import Process, broadcast_per_frame

SCHEDULING_MATRICES = ("full_sequence", "pyramid", "autoregressive")
SAMPLERS = ("ddim", "ddpm", "euler")


def scheduling_matrix(kind: str, num_steps: int, horizon: int) -> np.ndarray:
  """Rows = sampling iterations, columns = the ``horizon`` new frames; int indices in ``[0, S]``.

  ``full_sequence``   all frames together: ``m[i, j] = S - i`` (S+1 rows).
  ``pyramid``         each later frame lags one level: ``m[i, j] = clip(S + j - i, 0, S)``.
  ``autoregressive``  one frame after the other: ``m[i, j] = clip(S (j + 1) - i, 0, S)``.
  The first row is all ``S`` and the last all ``0``.
  """
  s, j = num_steps, np.arange(horizon)[None, :]
  if kind == "full_sequence":
    i = np.arange(s + 1)[:, None]
    return np.broadcast_to(s - i, (s + 1, horizon)).astype(np.int32)
  if kind == "pyramid":
    i = np.arange(s + horizon)[:, None]
    return np.clip(s + j - i, 0, s).astype(np.int32)
  if kind == "autoregressive":
    i = np.arange(s * horizon + 1)[:, None]
    return np.clip(s * (j + 1) - i, 0, s).astype(np.int32)
  raise ValueError(f"scheduling matrix must be one of {SCHEDULING_MATRICES}, got {kind!r}")


@dataclasses.dataclass(frozen=True)
class SamplerConfig:
  """How a window is sampled.

  ``sampler`` (:data:`SAMPLERS`): ``ddim`` (deterministic at ``eta=0``, ancestral noise as
  ``eta`` rises to 1) and ``ddpm`` (ancestral) for Gaussian processes, ``euler`` for flow
  matching; ``num_steps`` of them per window, spaced evenly in the process's time.
  ``matrix`` (:data:`SCHEDULING_MATRICES`, see :func:`scheduling_matrix`): ``full_sequence``
  (every new frame at one level), ``pyramid`` (each later frame a level behind) or
  ``autoregressive`` (one frame after the other). ``context_level`` is the stabilisation level
  at which clean context frames are shown (a DDPM level, e.g. 15 of 1000, or a flow time such as
  0.01). ``guidance_scale`` w gives
  ``out = out_null + w (out_cond - out_null)``; 1 disables guidance. ``clip_denoised`` clips the
  x0 estimate to [-1, 1] at every step (pixel-space models). ``kv_cache`` runs the context
  frames through the network once per window and keeps their temporal keys and values, so each
  step computes only the new frames (exact, and only allowed, with causal temporal attention).
  ``context_shares_level`` tells the network the new frames' level for the context frames too
  (IRASim's code, one timestep per sample; the context frames are still shown as
  ``context_level`` makes them): ``full_sequence`` only, without ``kv_cache``.
  """

  sampler: str = "ddim"
  num_steps: int = 10
  eta: float = 0.0
  matrix: str = "full_sequence"
  context_level: float = 15.0
  guidance_scale: float = 1.0
  clip_denoised: bool = False
  kv_cache: bool = False
  context_shares_level: bool = False

  def __post_init__(self):
    if self.sampler not in SAMPLERS:
      raise ValueError(f"sampler must be one of {SAMPLERS}, got {self.sampler!r}")
    if self.matrix not in SCHEDULING_MATRICES:
      raise ValueError(f"scheduling matrix must be one of {SCHEDULING_MATRICES}, got {self.matrix!r}")
    if self.num_steps < 1:
      raise ValueError(f"num_steps must be >= 1, got {self.num_steps}")
    if self.eta < 0:
      raise ValueError(f"eta must be >= 0, got {self.eta}")
    if self.context_shares_level and (self.matrix != "full_sequence" or self.kv_cache):
      raise ValueError(f"context_shares_level needs one level for all new frames and a context "
                       f"run at every step: matrix='full_sequence' and kv_cache=False, got "
                       f"matrix={self.matrix!r}, kv_cache={self.kv_cache}")

  def model_calls(self, horizon: int) -> int:
    """Network evaluations per block (doubled batch when guidance is on)."""
    return len(scheduling_matrix(self.matrix, self.num_steps, horizon)) - 1


def _denoised(process: Process, x: jax.Array, level: jax.Array, out: jax.Array,
              clip: bool) -> tuple[jax.Array, jax.Array]:
  x0, eps = process.to_x0_eps(x, level, out)
  if clip:
    x0 = jnp.clip(x0, -1.0, 1.0)
    eps = process.eps_from_x0(x, level, x0)
  return x0, eps


def ddim_step(process: Process, x: jax.Array, level_from: jax.Array, level_to: jax.Array,
              out: jax.Array, key: jax.Array, eta: float = 0.0, clip: bool = False) -> jax.Array:
  """DDIM from ``level_from`` to ``level_to`` (``[B, T]`` each) given the network output.

  ``x' = sqrt(ab') x0 + sqrt(1 - ab' - sigma^2) eps + sigma z`` with
  ``sigma = eta sqrt((1 - ab') / (1 - ab)) sqrt(1 - ab / ab')``; eta = 1 is DDPM ancestral
  sampling (the exact posterior ``q(x' | x, x0)``). Frames whose level does not change are kept.
  """
  x0, eps = _denoised(process, x, level_from, out, clip)
  ab = broadcast_per_frame(process.abar(level_from), x)
  ab_to = broadcast_per_frame(process.abar(level_to), x)
  sigma = eta * jnp.sqrt((1.0 - ab_to) / jnp.maximum(1.0 - ab, 1e-12) * (1.0 - ab / ab_to))
  direction = jnp.sqrt(jnp.maximum(1.0 - ab_to - sigma ** 2, 0.0))
  new = jnp.sqrt(ab_to) * x0 + direction * eps
  if eta > 0:
    new = new + sigma * jax.random.normal(key, x.shape, x.dtype)
  return jnp.where(broadcast_per_frame(level_from == level_to, x), x, new)


def euler_step(process: Process, x: jax.Array, level_from: jax.Array, level_to: jax.Array,
               out: jax.Array, clip: bool = False) -> jax.Array:
  """Flow-matching Euler step ``x + (t' - t) v``; frames with ``t' == t`` are unchanged.

  Written as ``(1 - t') x0 + t' eps`` of the current estimates, which is the same step and lets
  the x0 estimate be clipped.
  """
  x0, eps = _denoised(process, x, level_from, out, clip)
  new = process.add_noise(x0, level_to, eps)
  return jnp.where(broadcast_per_frame(level_from == level_to, x), x, new)


def sampler_step(process: Process, config: SamplerConfig, x, level_from, level_to, out, key):
  """One step of ``config.sampler`` (checked against the process: ddim/ddpm Gaussian, euler flow)."""
  if config.sampler not in process.samplers:
    raise ValueError(f"sampler {config.sampler!r} does not fit {type(process).__name__}; "
                     f"expected one of {process.samplers}")
  if config.sampler == "euler":
    return euler_step(process, x, level_from, level_to, out, config.clip_denoised)
  eta = 1.0 if config.sampler == "ddpm" else config.eta
  return ddim_step(process, x, level_from, level_to, out, key, eta, config.clip_denoised)


def classifier_free_guidance(out_cond: jax.Array, out_null: jax.Array, scale: float) -> jax.Array:
  """``out_null + scale (out_cond - out_null)``."""
  return out_null + scale * (out_cond - out_null)


DenoiseFn = Callable[[jax.Array, jax.Array], jax.Array]


def context_inputs(process: Process, config: SamplerConfig, context: jax.Array
                   ) -> tuple[jax.Array, jax.Array]:
  """Clean context frames ``[B, c, ...]`` as the network sees them during sampling: at
  ``config.context_level`` (scaled, no noise). Returns ``(inputs [B, c, ...], levels [B, c])``."""
  b, c = context.shape[:2]
  level = process.level(config.context_level)
  return process.context_input(context, level), jnp.full((b, c), level)


def window_denoiser(denoise_window: DenoiseFn, context_in: jax.Array,
                    context_levels: jax.Array, shared_level: bool = False) -> DenoiseFn:
  """A new-frame denoiser from one over whole windows: the fixed context is put in front of the
  new frames ``[B, h, ...]`` and the output for the new frames is returned. With
  ``shared_level`` the context frames are given the first new frame's level instead of
  ``context_levels [B, c]``."""
  c = context_in.shape[1]

  def denoise(x_new, levels_new):
    window = jnp.concatenate([context_in.astype(x_new.dtype), x_new], axis=1)
    own = (jnp.broadcast_to(levels_new[:, :1], context_levels.shape) if shared_level
           else context_levels.astype(levels_new.dtype))
    levels = jnp.concatenate([own, levels_new], axis=1)
    return denoise_window(window, levels)[:, c:]

  return denoise


def sample_window(denoise_fn: DenoiseFn, process: Process, config: SamplerConfig,
                  noise: jax.Array, key: jax.Array) -> jax.Array:
  """Denoise ``h`` new frames, starting at ``noise [B, h, ...]``; one ``lax.scan`` over the rows
  of the scheduling matrix.

  ``denoise_fn(x [B, h, ...], levels [B, h]) -> out [B, h, ...]`` gives the network output for the
  new frames; it holds the clean context (:func:`window_denoiser`, or a temporal KV cache).
  Returns ``[B, h, ...]``.
  """
  b, h = noise.shape[:2]
  matrix = scheduling_matrix(config.matrix, config.num_steps, h)
  levels = process.sampling_levels(config.num_steps)[matrix]  # [R, h]

  def body(x, row):
    level_from, level_to, step_key = row
    level_from = jnp.broadcast_to(level_from, (b, h))
    level_to = jnp.broadcast_to(level_to, (b, h))
    out = denoise_fn(x, level_from)
    return sampler_step(process, config, x, level_from, level_to, out, step_key), None

  keys = jax.random.split(key, len(levels) - 1)
  x, _ = jax.lax.scan(body, noise, (levels[:-1], levels[1:], keys))
  return x
