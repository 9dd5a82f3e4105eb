"""Forward processes, prediction targets and the training loss, with one noise level per frame.

Two processes share one interface so that the samplers and the rollout are written once:

* :class:`GaussianDiffusion` — discrete DDPM process over ``T`` levels. A level is an integer in
  ``[-1, T-1]`` where ``-1`` means clean (``abar = 1``). The network predicts ``eps``, ``v`` or
  ``x0``; ``v = sqrt(abar) eps - sqrt(1 - abar) x0``.
* :class:`FlowMatching` — rectified flow (WorldGym): a level is ``t`` in ``[0, 1]``,
  ``x_t = (1 - t) x0 + t eps`` and the network predicts the velocity ``eps - x0``.
* :class:`Regression` — no diffusion: a deterministic predictor trained by MSE. The frames to
  predict are shown as pure noise (level 1), as the sampler starts them, and the network
  outputs them (``x0``) in one step. The same network as the diffusion models, so it tells
  whether it can place what it must predict.

Videos are ``[B, T, H, W, C]`` and levels ``[B, T]``: one level per frame.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Union

import jax
import jax.numpy as jnp
import numpy as np

from wmjax.diffusion import schedules

PREDICTIONS = ("eps", "v", "x0")
NOISE_REGIMES = ("irasim", "per_frame", "monotone", "autoregressive")
LEVEL_DISTRIBUTIONS = ("default", "uniform", "logit_normal")


@dataclasses.dataclass(frozen=True)
class LevelSampling:
  """How training draws a frame's noise level, as a fraction ``u`` of the way from clean to
  pure noise: ``'uniform'`` (DDPM), ``'logit_normal'`` (``u = sigmoid(loc + scale * N(0, 1))``,
  SD3; ``loc > 0`` puts more of the training at high noise, where a frame has to come from its
  past and its action) or ``'default'`` (the process's own: uniform for Gaussian diffusion,
  logit-normal(0, 1) for flow matching)."""

  distribution: str = "default"
  loc: float = 0.0
  scale: float = 1.0

  def __post_init__(self):
    if self.distribution not in LEVEL_DISTRIBUTIONS:
      raise ValueError(f"level distribution must be one of {LEVEL_DISTRIBUTIONS}, got "
                       f"{self.distribution!r}")
    if self.scale <= 0:
      raise ValueError(f"level scale must be > 0, got {self.scale}")

  @classmethod
  def from_config(cls, diffusion) -> "LevelSampling":
    """From a ``config.diffusion`` section (:class:`wmjax.config.DiffusionConfig`)."""
    return cls(diffusion.level_distribution, diffusion.level_loc, diffusion.level_scale)

  def fractions(self, rng: jax.Array, shape: tuple[int, ...], default: str) -> jax.Array:
    """Fractions in ``[0, 1]`` of ``shape``; ``default`` stands for ``'default'``."""
    distribution = default if self.distribution == "default" else self.distribution
    if distribution == "uniform":
      return jax.random.uniform(rng, shape)
    return jax.nn.sigmoid(self.loc + self.scale * jax.random.normal(rng, shape))


def broadcast_per_frame(values: jax.Array, like: jax.Array) -> jax.Array:
  """Broadcast per-frame values ``[B, T]`` against a video ``[B, T, ...]``."""
  return values.reshape(values.shape + (1,) * (like.ndim - values.ndim))


@dataclasses.dataclass(frozen=True, eq=False)
class GaussianDiffusion:
  """Discrete Gaussian diffusion; ``alphas_cumprod [T]`` from :mod:`wmjax.diffusion.schedules`."""

  alphas_cumprod: np.ndarray
  prediction: str = "eps"

  clean_level = -1
  samplers = ("ddim", "ddpm", "pndm", "pndm_prk", "dpm_solver++")

  def __post_init__(self):
    if self.prediction not in PREDICTIONS:
      raise ValueError(f"prediction must be one of {PREDICTIONS}, got {self.prediction!r}")

  @classmethod
  def create(cls, schedule: str = "linear", num_timesteps: int = 1000,
             prediction: str = "eps") -> "GaussianDiffusion":
    betas = schedules.make_betas(schedule, num_timesteps)
    return cls(schedules.alphas_cumprod(betas), prediction)

  @property
  def num_timesteps(self) -> int:
    return len(self.alphas_cumprod)

  def abar(self, levels: jax.Array) -> jax.Array:
    """Signal ``abar`` at integer levels in ``[-1, T-1]`` (``-1`` -> 1.0); float32, same shape."""
    table = jnp.asarray(np.concatenate([[1.0], self.alphas_cumprod]), jnp.float32)
    return table[jnp.asarray(levels, jnp.int32) + 1]

  def model_time(self, levels: jax.Array) -> jax.Array:
    """The timestep the network is shown: the level itself, clean frames as 0."""
    return jnp.maximum(jnp.asarray(levels, jnp.float32), 0.0)

  def add_noise(self, x0: jax.Array, levels: jax.Array, noise: jax.Array) -> jax.Array:
    """q_sample: ``sqrt(abar) x0 + sqrt(1 - abar) eps`` with per-frame ``abar``."""
    ab = broadcast_per_frame(self.abar(levels), x0)
    return jnp.sqrt(ab) * x0 + jnp.sqrt(1.0 - ab) * noise

  def target(self, x0: jax.Array, noise: jax.Array, levels: jax.Array) -> jax.Array:
    """What the network is trained to output: eps, v or x0."""
    if self.prediction == "eps":
      return noise
    if self.prediction == "x0":
      return x0
    ab = broadcast_per_frame(self.abar(levels), x0)
    return jnp.sqrt(ab) * noise - jnp.sqrt(1.0 - ab) * x0

  def to_x0_eps(self, x_t: jax.Array, levels: jax.Array,
                out: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Network output -> (x0, eps) estimates, per frame."""
    ab = broadcast_per_frame(self.abar(levels), x_t)
    sa, s1a = jnp.sqrt(ab), jnp.sqrt(1.0 - ab)
    if self.prediction == "v":
      x0 = sa * x_t - s1a * out
      return x0, sa * out + s1a * x_t
    if self.prediction == "eps":
      return (x_t - s1a * out) / sa, out
    return out, self.eps_from_x0(x_t, levels, out)

  def eps_from_x0(self, x_t: jax.Array, levels: jax.Array, x0: jax.Array) -> jax.Array:
    """The noise that takes ``x0`` to ``x_t`` at ``levels``."""
    ab = broadcast_per_frame(self.abar(levels), x_t)
    return (x_t - jnp.sqrt(ab) * x0) / jnp.sqrt(jnp.maximum(1.0 - ab, 1e-12))

  def context_input(self, x0: jax.Array, level: float) -> jax.Array:
    """A clean context frame as shown at ``level``: scaled by ``sqrt(abar)``, no noise added."""
    return jnp.sqrt(self.abar(jnp.asarray(int(level)))) * x0

  def sample_levels(self, rng: jax.Array, shape: tuple[int, ...],
                    sampling: LevelSampling = LevelSampling()) -> jax.Array:
    """Integer training levels in ``[0, T-1]``, uniform by default."""
    if sampling.distribution in ("default", "uniform"):
      return jax.random.randint(rng, shape, 0, self.num_timesteps)
    u = sampling.fractions(rng, shape, default="uniform")
    return jnp.minimum(jnp.floor(u * self.num_timesteps), self.num_timesteps - 1).astype(jnp.int32)

  def sampling_levels(self, num_steps: int) -> np.ndarray:
    """The ``num_steps + 1`` levels a sampler visits: ``round(linspace(-1, T-1, S+1))``; index 0 is clean."""
    return np.round(np.linspace(-1, self.num_timesteps - 1, num_steps + 1)).astype(np.int32)

  def level(self, value: float) -> int:
    """A configured level (e.g. the stabilisation level) in this process's units."""
    return int(value)


@dataclasses.dataclass(frozen=True, eq=False)
class FlowMatching:
  """Rectified flow with velocity target ``eps - x0``; ``num_timesteps`` scales the model time."""

  num_timesteps: int = 1000

  clean_level = 0.0
  samplers = ("euler",)
  prediction = "velocity"

  def model_time(self, levels: jax.Array) -> jax.Array:
    return jnp.asarray(levels, jnp.float32) * self.num_timesteps

  def add_noise(self, x0, levels, noise):
    t = broadcast_per_frame(jnp.asarray(levels, jnp.float32), x0)
    return (1.0 - t) * x0 + t * noise

  def target(self, x0, noise, levels):
    del levels
    return noise - x0

  def to_x0_eps(self, x_t, levels, out):
    t = broadcast_per_frame(jnp.asarray(levels, jnp.float32), x_t)
    return x_t - t * out, x_t + (1.0 - t) * out

  def eps_from_x0(self, x_t, levels, x0):
    t = broadcast_per_frame(jnp.asarray(levels, jnp.float32), x_t)
    return (x_t - (1.0 - t) * x0) / jnp.maximum(t, 1e-12)

  def context_input(self, x0, level):
    return (1.0 - float(level)) * x0

  def sample_levels(self, rng, shape, sampling: LevelSampling = LevelSampling()):
    """Training times ``t``, logit-normal ``sigmoid(N(0, 1))`` by default."""
    return sampling.fractions(rng, shape, default="logit_normal")

  def sampling_levels(self, num_steps: int) -> np.ndarray:
    return np.linspace(0.0, 1.0, num_steps + 1, dtype=np.float32)

  def level(self, value: float) -> float:
    return float(value)


@dataclasses.dataclass(frozen=True, eq=False)
class Regression:
  """Deterministic prediction by MSE: level 1 shows a frame as pure noise, level 0 clean.

  Train with ``regime='irasim'`` (clean context, noise for the targets, which carries nothing
  about them); sampling is one step
  (``sampling.num_steps=1``, ``sampler='euler'``, ``context_level=0``). The network learns the
  conditional mean of the targets: blur where the future is uncertain, no noise.
  """

  num_timesteps: int = 1000

  clean_level = 0.0
  samplers = ("euler",)
  prediction = "x0"

  def model_time(self, levels):
    return jnp.asarray(levels, jnp.float32) * self.num_timesteps

  def add_noise(self, x0, levels, noise):
    t = broadcast_per_frame(jnp.asarray(levels, jnp.float32), x0)
    return (1.0 - t) * x0 + t * noise

  def target(self, x0, noise, levels):
    del noise, levels
    return x0

  def to_x0_eps(self, x_t, levels, out):
    del x_t, levels
    return out, jnp.zeros_like(out)

  def eps_from_x0(self, x_t, levels, x0):
    del x_t, levels
    return jnp.zeros_like(x0)

  def context_input(self, x0, level):
    return (1.0 - float(level)) * x0

  def sample_levels(self, rng, shape, sampling: LevelSampling = LevelSampling()):
    del rng, sampling
    return jnp.ones(shape, jnp.float32)

  def sampling_levels(self, num_steps: int) -> np.ndarray:
    if num_steps != 1:
      raise ValueError(f"diffusion.kind='regression' predicts in one step: sampling.num_steps "
                       f"must be 1, got {num_steps}")
    return np.array([0.0, 1.0], np.float32)

  def level(self, value: float) -> float:
    return float(value)


Process = Union[GaussianDiffusion, FlowMatching, Regression]


def make_process(kind: str = "gaussian", schedule: str = "linear", num_timesteps: int = 1000,
                 prediction: str = "eps") -> Process:
  """``kind='gaussian'`` (with schedule and prediction), ``'flow'`` or ``'regression'``."""
  if kind == "gaussian":
    return GaussianDiffusion.create(schedule, num_timesteps, prediction)
  if kind == "flow":
    return FlowMatching(num_timesteps)
  if kind == "regression":
    return Regression(num_timesteps)
  raise ValueError(f"diffusion kind must be 'gaussian', 'flow' or 'regression', got {kind!r}")


def training_levels(process: Process, rng: jax.Array, batch: int, frames: int,
                    regime: str = "per_frame", num_context: int = 1,
                    sampling: LevelSampling = LevelSampling()) -> tuple[jax.Array, jax.Array]:
  """Noise levels ``[B, T]`` and the loss mask ``[B, T]`` of one training batch; every level
  the regime leaves noisy is drawn by ``sampling``.

  ``irasim``: the first ``num_context`` frames are clean and excluded from the loss; the predicted
  frames share one level per sample. ``per_frame`` (WPE, diffusion forcing): an independent level
  for every frame, every frame in the loss. ``monotone``: the same independent levels sorted
  along time, so that no frame is cleaner than one before it. That is the pattern of every
  scheduling matrix (full sequence, pyramid, autoregressive); under causal attention a frame's
  prediction then always comes from a past at most as noisy as itself, and no training goes to
  a later frame cleaner than an earlier one, which sampling never shows.
  ``autoregressive`` (teacher forcing): one frame ``k >= num_context`` per sample, drawn
  uniformly, is noised and alone in the loss; the frames before it are clean. That is what
  sampling one frame after the other (the ``autoregressive`` scheduling matrix) asks of a causal
  network: every prediction from a clean past. The frames after ``k`` take independent levels;
  under causal attention they cannot reach frame ``k``.
  """
  if regime in ("per_frame", "monotone"):
    levels = process.sample_levels(rng, (batch, frames), sampling)
    if regime == "monotone":
      levels = jnp.sort(levels, axis=1)
    return levels, jnp.ones((batch, frames), jnp.float32)
  if regime in ("irasim", "autoregressive"):
    if not 0 < num_context < frames:
      raise ValueError(f"num_context must be in [1, {frames - 1}] for {frames} frames, "
                       f"got {num_context}")
    if regime == "autoregressive":
      frame_key, level_key = jax.random.split(rng)
      target = jax.random.randint(frame_key, (batch, 1), num_context, frames)
      steps = jnp.arange(frames)[None, :]
      levels = process.sample_levels(level_key, (batch, frames), sampling)
      levels = jnp.where(steps < target, jnp.asarray(process.clean_level, levels.dtype), levels)
      return levels, (steps == target).astype(jnp.float32)
    shared = process.sample_levels(rng, (batch, 1), sampling)
    is_context = jnp.arange(frames)[None, :] < num_context
    levels = jnp.where(is_context, jnp.asarray(process.clean_level, shared.dtype), shared)
    return levels, jnp.broadcast_to(~is_context, (batch, frames)).astype(jnp.float32)
  raise ValueError(f"noise regime must be one of {NOISE_REGIMES}, got {regime!r}")


def diffusion_loss(denoise_fn: Callable[[jax.Array, jax.Array], jax.Array], process: Process,
                   x0: jax.Array, rng: jax.Array, regime: str = "per_frame",
                   num_context: int = 1, sampling: LevelSampling = LevelSampling()
                   ) -> tuple[jax.Array, dict]:
  """Unweighted MSE between the network output and the process's target on the loss frames.

  ``denoise_fn(x_t, levels)`` runs the network on the noisy video ``[B, T, H, W, C]`` at the
  process's levels ``[B, T]`` (integers in ``[-1, T-1]`` for Gaussian diffusion, ``t`` in
  ``[0, 1]`` for flow matching). The levels are not what the network is shown: convert them with
  ``process.model_time`` inside ``denoise_fn``, as :mod:`wmjax.train.step` does::

      def denoise_fn(x_t, levels):
        return network.apply(params, x_t, process.model_time(levels), actions)

  (a network given flow-matching levels directly would see times 1000 times too small and train
  without a word). Returns ``(loss, aux)`` with the per-frame loss ``[B, T]`` and the levels in
  ``aux``."""
  levels, mask, noise = training_noise(process, rng, x0.shape, regime, num_context, sampling)
  loss_sum, per_frame = masked_loss_sum(denoise_fn, process, x0, levels, noise, mask)
  return loss_sum / mask.sum(), {"per_frame_loss": per_frame, "levels": levels, "loss_mask": mask}


def training_noise(process: Process, rng: jax.Array, shape: tuple[int, ...],
                   regime: str = "per_frame", num_context: int = 1,
                   sampling: LevelSampling = LevelSampling()
                   ) -> tuple[jax.Array, jax.Array, jax.Array]:
  """The random part of one training batch of videos ``shape = [B, T, ...]``: levels ``[B, T]``,
  loss mask ``[B, T]`` (:func:`training_levels`) and Gaussian noise of ``shape``."""
  level_rng, noise_rng = jax.random.split(rng)
  levels, mask = training_levels(process, level_rng, shape[0], shape[1], regime, num_context,
                                 sampling)
  return levels, mask, jax.random.normal(noise_rng, shape, jnp.float32)


# A value shows an object when it differs from its frame's median (the background) by more than
# this in some channel (model units: 0.05 is about 6 of 255 grey levels of a pixel codec's [-1, 1]).
OBJECT_THRESHOLD = 0.05


def object_mask(frames: jax.Array, dilation: int) -> jax.Array:
  """Where frames ``[..., H, W, C]`` show an object: ``[..., H, W, 1]``, 1.0 where a value
  differs from its frame's median (the background) by more than :data:`OBJECT_THRESHOLD` in some
  channel, grown by ``dilation`` pixels; 0.0 elsewhere."""
  median = jnp.median(frames, axis=(-3, -2), keepdims=True)
  objects = jnp.max(jnp.abs(frames - median), axis=-1, keepdims=True) > OBJECT_THRESHOLD
  objects = objects.astype(jnp.float32)
  if dilation:
    size = 2 * dilation + 1
    window = (1,) * (frames.ndim - 3) + (size, size, 1)
    objects = jax.lax.reduce_window(objects, 0.0, jax.lax.max, window, (1,) * frames.ndim, "SAME")
  return objects


def object_weights(x0: jax.Array, object_weight: float, dilation: int) -> jax.Array:
  """Per-value loss weights ``[B, T, H, W, 1]`` of a clean video ``x0 [B, T, H, W, C]``:
  ``1 + object_weight`` where the *previous* frame shows an object (:func:`object_mask`), grown
  by ``dilation`` pixels so that it covers where an object can move in one frame; 1 elsewhere
  and on the first frame.

  A small object (a 3-pixel agent) is a fraction of a percent of an unweighted MSE, which a
  network can leave out and still beat copying the last frame. The weights depend on the
  previous frame only, which the network sees clean as context (the ``irasim`` and
  ``autoregressive`` regimes), so they do not move the loss's minimiser, the posterior mean of
  the frame: weights read from the frame being predicted (say, where it differs from the previous
  one) would, and a sampler then draws the object wherever it might be."""
  objects = object_mask(x0[:, :-1], dilation)
  objects = jnp.concatenate([jnp.zeros_like(objects[:, :1]), objects], axis=1)
  return 1.0 + object_weight * objects


def masked_loss_sum(denoise_fn: Callable[[jax.Array, jax.Array], jax.Array], process: Process,
                    x0: jax.Array, levels: jax.Array, noise: jax.Array, mask: jax.Array,
                    object_weight: float = 0.0, object_dilation: int = 0
                    ) -> tuple[jax.Array, jax.Array]:
  """(sum over the loss frames of the per-frame MSE, per-frame MSE ``[B, T]``) for given levels
  and noise; summing it over slices of a batch and dividing by ``mask.sum()`` of the whole batch
  gives :func:`diffusion_loss` of the whole batch (gradient accumulation). ``object_weight > 0``
  weights the values near the objects of the previous frame (:func:`object_weights`)."""
  b, t = x0.shape[:2]
  out = denoise_fn(process.add_noise(x0, levels, noise.astype(x0.dtype)), levels)
  err = jnp.square(out.astype(jnp.float32) - process.target(x0, noise.astype(x0.dtype), levels))
  if object_weight:
    err = err * object_weights(x0.astype(jnp.float32), object_weight, object_dilation)
  per_frame = err.reshape(b, t, -1).mean(-1)
  return (per_frame * mask).sum(), per_frame
