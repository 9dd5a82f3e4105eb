"""Samplers with per-frame noise levels, scheduling matrices and classifier-free guidance.

A sampling run over a window of ``h`` new frames follows a *scheduling matrix* (diffusion
forcing): row ``i`` gives, for every new frame, an index into the sampler's stages (``S`` = pure
noise, ``0`` = clean; a stage is one of the process's sampling levels or the midpoint of a
step, and PNDM visits some levels more than once, :meth:`SamplerConfig.stage_levels`). Each
row-to-row transition is one network call and one sampler step; frames whose stage does not
change keep their values.

The multistep samplers (``pndm``, ``pndm_prk``, ``dpm_solver++``) keep, per frame, what their
next steps need of the past (:func:`init_memory`) in the loop state, so with the
``autoregressive`` matrix every frame runs its own chain of steps.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmjax.diffusion.objectives import Process, broadcast_per_frame

SCHEDULING_MATRICES = ("full_sequence", "pyramid", "autoregressive")
SAMPLERS = ("ddim", "ddpm", "euler", "pndm", "pndm_prk", "dpm_solver++")
MULTISTEP_SAMPLERS = ("pndm", "pndm_prk", "dpm_solver++")


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

  ``sampler`` (:data:`SAMPLERS`): for Gaussian processes ``ddim`` (deterministic at ``eta=0``,
  ancestral noise as ``eta`` rises to 1), ``ddpm`` (ancestral), ``pndm`` (pseudo linear
  multistep on the noise estimate: diffusers' ``PNDMScheduler(skip_prk_steps=True)``,
  :func:`pndm_step`), ``pndm_prk`` (the same after a pseudo Runge-Kutta warm-up of three steps
  of four network calls each: ``PNDMScheduler(skip_prk_steps=False)``, as IRASim evaluates) and
  ``dpm_solver++`` (DPM-Solver++ 2M: diffusers'
  ``DPMSolverMultistepScheduler(algorithm_type="dpmsolver++", solver_order=2)``,
  :func:`dpm_solver_step`); ``euler`` for flow matching. ``num_steps`` of them per window,
  spaced evenly in the process's time (diffusers' ``timestep_spacing="trailing"``); ``pndm``
  makes one more network call than it has steps (its warm-up evaluates the second level twice),
  ``pndm_prk`` nine more (50 steps: 59 calls), see :attr:`num_stages`. IRASim's scheduler config
  says ``timestep_spacing="linspace"``: diffusers then starts its steps at the levels
  ``round(linspace(0, T-1, S))`` (the lowest is 0, not ``T/S - 1``) while its transfers still
  move by ``T // S``; the levels here are diffusers' ``"trailing"`` ones, and ``pndm_prk`` is
  ``PNDMScheduler(skip_prk_steps=False, timestep_spacing="trailing", set_alpha_to_one=True)``
  call by call when ``S`` divides ``T``. ``eta`` is for ``ddim`` only: the multistep samplers are
  deterministic.
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
    if self.eta and self.sampler in MULTISTEP_SAMPLERS:
      raise ValueError(f"eta={self.eta} is for the ddim sampler; {self.sampler!r} is deterministic "
                       f"(set eta=0 or sampler='ddim')")
    if self.context_shares_level and (self.matrix != "full_sequence" or self.kv_cache):
      raise ValueError(f"context_shares_level needs one level for all new frames and a context "
                       f"run at every step: matrix='full_sequence' and kv_cache=False, got "
                       f"matrix={self.matrix!r}, kv_cache={self.kv_cache}")

  @property
  def runge_kutta_steps(self) -> int:
    """Steps of ``pndm_prk``'s Runge-Kutta warm-up: diffusers' three, or every step below four
    (where diffusers' warm-up would stop short of clean)."""
    return min(3, self.num_steps) if self.sampler == "pndm_prk" else 0

  @property
  def num_stages(self) -> int:
    """Network calls in one frame's chain: ``num_steps``, one more for ``pndm`` (``num_steps >= 2``:
    its first step is taken twice, an Euler predictor and a trapezoidal corrector), three more
    per Runge-Kutta step for ``pndm_prk``."""
    return (self.num_steps + int(self.sampler == "pndm" and self.num_steps > 1)
            + 3 * self.runge_kutta_steps)

  def stage_levels(self) -> np.ndarray:
    """``[num_stages + 1]`` indices into :func:`half_step_levels` (``2 k``: sampling level ``k``,
    ``2 k - 1``: the midpoint of the step from it), one per stage of a frame's chain (``0`` =
    clean). PNDM's predictor and corrector both end at sampling level ``S - 1``; a Runge-Kutta
    step from level ``k`` visits ``2 k, 2 k - 1, 2 k - 1, 2 k - 2``."""
    s, rk = self.num_steps, self.runge_kutta_steps
    if self.sampler == "pndm" and s > 1:
      warm_up, rest = [[2 * s, 2 * s - 2]], s - 1
    else:
      warm_up = [[2 * k, 2 * k - 1, 2 * k - 1, 2 * k - 2] for k in range(s, s - rk, -1)]
      rest = s - rk
    chain = np.concatenate([*warm_up, 2 * np.arange(rest, -1, -1)])
    return chain[::-1].astype(np.int32)

  def stage_sources(self) -> np.ndarray:
    """``[num_stages]``: for each step of a frame's chain, how many stages back the sample it
    moves from was taken (``0``: the frame's current sample; PNDM's corrector and the later calls
    of a Runge-Kutta step move from the sample where that step started)."""
    sources = np.zeros(self.num_stages, np.int32)
    sources[:4 * self.runge_kutta_steps] = np.tile(np.arange(4), self.runge_kutta_steps)
    if self.sampler == "pndm" and self.num_steps > 1:
      sources[1] = 1
    return sources

  def model_calls(self, horizon: int) -> int:
    """Network evaluations per block (doubled batch when guidance is on)."""
    return len(scheduling_matrix(self.matrix, self.num_stages, horizon)) - 1


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


def _check_fits(process: Process, config: SamplerConfig) -> None:
  if config.sampler not in process.samplers:
    raise ValueError(f"sampler {config.sampler!r} does not fit {type(process).__name__}; "
                     f"expected one of {process.samplers}")


def sampler_step(process: Process, config: SamplerConfig, x, level_from, level_to, out, key):
  """One step of a one-step sampler (ddim/ddpm Gaussian, euler flow; checked against the
  process). The multistep samplers need their memory: :func:`sampler_update`."""
  _check_fits(process, config)
  if config.sampler in MULTISTEP_SAMPLERS:
    raise ValueError(f"sampler {config.sampler!r} is a multistep method: step it with "
                     f"sampler_update and its memory from init_memory")
  if config.sampler == "euler":
    return euler_step(process, x, level_from, level_to, out, config.clip_denoised)
  eta = 1.0 if config.sampler == "ddpm" else config.eta
  return ddim_step(process, x, level_from, level_to, out, key, eta, config.clip_denoised)


class FrameSteps(NamedTuple):
  """Where every frame stands in its own chain at one row-to-row transition of a scheduling
  matrix; each field ``[B, h]`` (or ``[R, h]`` for all rows, :func:`frame_steps`).

  ``level_from``: the frame's level, at which the network sees it; ``level_to``: the level the
  step takes it to; ``level_last``: its level one stage earlier (where DPM-Solver++'s previous
  x0 estimate was made; meaningless at ``index == 0``); ``level_source``: the level of the
  sample the step moves from (``level_from``, or for PNDM's corrector and the later calls of a
  Runge-Kutta step the level where that step started, :meth:`SamplerConfig.stage_sources`);
  ``index``: how many stages of its chain the frame has taken; ``moving``: whether it takes one
  now (the others keep their value and memory).
  """

  level_from: jax.Array
  level_to: jax.Array
  level_last: jax.Array
  level_source: jax.Array
  index: jax.Array
  moving: jax.Array


def half_step_levels(process: Process, num_steps: int) -> np.ndarray:
  """The process's ``num_steps + 1`` sampling levels with the midpoint of every step between
  them, ``[2 S + 1]`` (entry ``2 k`` is sampling level ``k``). Integer midpoints round down,
  ``t' + (t - t') // 2``: diffusers' PNDM level ``t' + T // S // 2`` when ``S`` divides ``T``."""
  levels = process.sampling_levels(num_steps)
  half = np.empty(2 * num_steps + 1, levels.dtype)
  half[0::2] = levels
  half[1::2] = levels[:-1] + np.diff(levels) / 2
  return half


def frame_steps(process: Process, config: SamplerConfig, horizon: int) -> FrameSteps:
  """The transitions of ``config``'s scheduling matrix over ``horizon`` frames, ``[R, h]`` each."""
  stages = config.num_stages
  matrix = scheduling_matrix(config.matrix, stages, horizon)
  levels = half_step_levels(process, config.num_steps)[config.stage_levels()]
  before, after = matrix[:-1], matrix[1:]
  index = stages - before
  back = np.append(config.stage_sources(), 0)[index]
  return FrameSteps(level_from=levels[before], level_to=levels[after],
                    level_last=levels[np.minimum(before + 1, stages)],
                    level_source=levels[before + back], index=index, moving=before != after)


# PLMS weights of [eps_now, eps_-1, eps_-2, eps_-3] by a frame's stage index (4 and on: Adams-
# Bashforth 4). Index 1 is the warm-up's corrector: the mean of the first two noise estimates.
PLMS_WEIGHTS = np.array([[1.0, 0.0, 0.0, 0.0],
                         [1 / 2, 1 / 2, 0.0, 0.0],
                         [3 / 2, -1 / 2, 0.0, 0.0],
                         [23 / 12, -16 / 12, 5 / 12, 0.0],
                         [55 / 24, -59 / 24, 37 / 24, -9 / 24]])
# The four calls of a Runge-Kutta step (at t, t - h/2, t - h/2, t - h) in its noise estimate.
RUNGE_KUTTA_WEIGHTS = np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6])


def pndm_weights(config: SamplerConfig) -> np.ndarray:
  """``[num_stages + 1, 6]``, a row per step of a frame's chain (the last for finished frames):
  the weights of ``[eps, eps_-1, eps_-2, eps_-3, rk]`` in the noise estimate the step moves with,
  ``rk`` being the Runge-Kutta sum after the step, and the weight with which ``eps`` joins it.
  ``pndm``: :data:`PLMS_WEIGHTS`; ``pndm_prk``: a Runge-Kutta step's first three calls move with
  their own estimate, its last with the sum, then Adams-Bashforth 4 (the warm-up left three
  estimates, each step's first)."""
  rk = config.runge_kutta_steps
  rows = np.zeros((config.num_stages + 1, 6))
  if rk:
    rows[:4 * rk, 0] = np.tile([1.0, 1.0, 1.0, 0.0], rk)
    rows[3:4 * rk:4, 4] = 1.0
    rows[:4 * rk, 5] = np.tile(RUNGE_KUTTA_WEIGHTS, rk)
    rows[4 * rk:-1, :4] = PLMS_WEIGHTS[-1]
  else:
    rows[:-1, :4] = PLMS_WEIGHTS[np.minimum(np.arange(config.num_stages), len(PLMS_WEIGHTS) - 1)]
  return rows


def init_memory(config: SamplerConfig, x: jax.Array) -> tuple[jax.Array, ...]:
  """A multistep sampler's per-frame memory, zeros like ``x [B, h, ...]``: for ``pndm`` the
  sample its corrector restarts from and the last three noise estimates, for ``pndm_prk`` the
  same (the sample a Runge-Kutta step started from) and the Runge-Kutta sum, for
  ``dpm_solver++`` the previous x0 estimate; empty for the one-step samplers."""
  size = {"pndm": 4, "pndm_prk": 5, "dpm_solver++": 1}.get(config.sampler, 0)
  return tuple(jnp.zeros_like(x) for _ in range(size))


def ddim_move(process: Process, x: jax.Array, level_from: jax.Array, level_to: jax.Array,
              eps: jax.Array) -> jax.Array:
  """Deterministic DDIM from ``level_from`` to ``level_to`` (``[B, h]``) along the noise ``eps``:
  ``sqrt(ab') x0 + sqrt(1 - ab') eps`` with ``x0 = (x - sqrt(1 - ab) eps) / sqrt(ab)`` (PNDM's
  transfer, formula (9) of Liu et al. 2022, is this step)."""
  ab = broadcast_per_frame(process.abar(level_from), x)
  x0 = (x - jnp.sqrt(1.0 - ab) * eps) / jnp.sqrt(ab)
  return process.add_noise(x0, level_to, eps)


def pndm_step(process: Process, x: jax.Array, memory: tuple[jax.Array, ...], step: FrameSteps,
              out: jax.Array, weights: np.ndarray, clip: bool = False
              ) -> tuple[jax.Array, tuple[jax.Array, ...]]:
  """PNDM, diffusers' ``PNDMScheduler``: PLMS (``pndm``, ``skip_prk_steps=True``) or PLMS after
  a pseudo Runge-Kutta warm-up (``pndm_prk``, ``skip_prk_steps=False``); ``weights`` is
  :func:`pndm_weights` of the sampler.

  Every step is a PNDM transfer (:func:`ddim_move`) to ``step.level_to`` along a combination of
  noise estimates, from the frame's sample or, where ``step.level_source`` is not the level the
  network sees (:meth:`SamplerConfig.stage_sources`), from the sample kept where the move began.
  PLMS: stage 0 moves one level with its estimate ``e0`` (Euler); stage 1 evaluates the network
  there again and redoes that move with ``(e0 + e1) / 2``; later stages move with
  Adams-Bashforth combinations of the current and up to three earlier estimates (the
  corrector's is not kept). A Runge-Kutta step from ``t`` to ``t - h`` moves to ``t - h/2``
  with ``e1`` (at ``t``), again with ``e2`` (at ``t - h/2``), to ``t - h`` with ``e3`` (at
  ``t - h/2``) and with ``(e1 + 2 e2 + 2 e3 + e4) / 6`` (``e4`` at ``t - h``), all from its
  start; ``e1`` is kept for the PLMS steps.
  ``memory = (start, eps_-1, eps_-2, eps_-3)`` and for ``pndm_prk`` the Runge-Kutta sum, each
  like ``x [B, h, ...]``; returns ``(x', memory')`` for every frame (the caller keeps the frames
  that do not move).
  """
  start, *past = memory
  past, rk_sum = past[:3], past[3:]
  _, eps = _denoised(process, x, step.level_from, out, clip)
  w = jnp.asarray(weights, x.dtype)[step.index]
  per_frame = lambda a: broadcast_per_frame(a, x)
  own = per_frame(step.level_source == step.level_from)
  rk_sum = [jnp.where(own, 0.0, total) + per_frame(w[..., 5]) * eps for total in rk_sum]
  combined = sum(per_frame(w[..., k]) * e for k, e in enumerate([eps, *past, *rk_sum]))
  start = jnp.where(own, x, start)
  new = ddim_move(process, start, step.level_source, step.level_to, combined)
  past = [jnp.where(own, pushed, old) for old, pushed in zip(past, [eps, *past[:-1]])]
  return new, (start, *past, *rk_sum)


def log_snr_half(process: Process, levels: jax.Array) -> jax.Array:
  """DPM-Solver's ``lambda = log(alpha / sigma) = (log(ab) - log(1 - ab)) / 2`` (+inf when clean)."""
  ab = process.abar(levels)
  return 0.5 * (jnp.log(ab) - jnp.log1p(-ab))


def dpm_solver_step(process: Process, x: jax.Array, memory: tuple[jax.Array, ...],
                    step: FrameSteps, out: jax.Array, clip: bool = False
                    ) -> tuple[jax.Array, tuple[jax.Array, ...]]:
  """DPM-Solver++ 2M (multistep, midpoint), diffusers' ``DPMSolverMultistepScheduler`` with
  ``algorithm_type="dpmsolver++"``, ``solver_order=2``, ``final_sigmas_type="zero"``.

  With ``lambda = log(alpha / sigma)``, ``h = lambda' - lambda``, ``r = (lambda - lambda_last) / h``
  and the x0 estimates ``D`` (now) and ``D_-1`` (the frame's previous stage):
  ``x' = (sigma' / sigma) x + alpha' (1 - e^-h) (D + (D - D_-1) / (2 r))``. A frame's first step
  and its last (to clean: diffusers' ``lower_order_final``) drop the correction (first order,
  which is DDIM). ``memory = (D_-1,)`` like ``x [B, h, ...]``; returns ``(x', memory')``.
  """
  (previous,) = memory
  x0, _ = _denoised(process, x, step.level_from, out, clip)
  second = (step.index > 0) & (step.level_to != process.clean_level)
  lam_from = log_snr_half(process, step.level_from)
  h = log_snr_half(process, step.level_to) - lam_from
  r = jnp.where(second, (lam_from - log_snr_half(process, step.level_last)) / h, 1.0)
  correction = (x0 - previous) / (2.0 * broadcast_per_frame(r, x))
  d = x0 + jnp.where(broadcast_per_frame(second, x), correction, 0.0)
  ab, ab_to = process.abar(step.level_from), process.abar(step.level_to)
  x_scale = broadcast_per_frame(jnp.sqrt((1.0 - ab_to) / (1.0 - ab)), x)
  d_scale = broadcast_per_frame(jnp.sqrt(ab_to) * -jnp.expm1(-h), x)
  return x_scale * x + d_scale * d, (x0,)


def sampler_update(process: Process, config: SamplerConfig, x: jax.Array,
                   memory: tuple[jax.Array, ...], step: FrameSteps, out: jax.Array,
                   key: jax.Array) -> tuple[jax.Array, tuple[jax.Array, ...]]:
  """One row transition of any sampler: ``x [B, h, ...]`` and its memory (:func:`init_memory`)
  after the network output ``out`` at ``step.level_from``. Frames that do not move keep both."""
  if config.sampler not in MULTISTEP_SAMPLERS:
    return sampler_step(process, config, x, step.level_from, step.level_to, out, key), memory
  _check_fits(process, config)
  if config.sampler == "dpm_solver++":
    new, new_memory = dpm_solver_step(process, x, memory, step, out, config.clip_denoised)
  else:
    new, new_memory = pndm_step(process, x, memory, step, out, pndm_weights(config),
                                config.clip_denoised)
  moving = broadcast_per_frame(step.moving, x)
  keep = lambda old, updated: jnp.where(moving, updated, old)
  return keep(x, new), tuple(map(keep, memory, new_memory))


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

  def body(carry, inputs):
    x, memory = carry
    step, step_key = inputs
    step = FrameSteps(*(jnp.broadcast_to(a, (b, h)) for a in step))
    out = denoise_fn(x, step.level_from)
    return sampler_update(process, config, x, memory, step, out, step_key), None

  steps = frame_steps(process, config, h)
  keys = jax.random.split(key, len(steps.index))
  (x, _), _ = jax.lax.scan(body, (noise, init_memory(config, noise)), (steps, keys))
  return x
