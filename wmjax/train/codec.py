"""Fitting a codec to a dataset's own frames (``wmjax data train-codec``).

A small AutoencoderKL (:mod:`wmjax.nn.vae`) is trained on frames of the config's training split
and written as a diffusers folder, which ``codec.kind='vae'`` with ``codec.path`` reads like any
downloaded VAE (and ``wmjax data encode`` pre-encodes with). For frames no published VAE was
trained on, or too small for one (a 48x48 Push-T render, where an SD VAE's 8x downsampling
leaves 6x6 latents).

The loss of a frame is the squared error of its reconstruction through a sample of the
posterior, weighted ``1 + object_weight`` near the frame's objects
(:func:`wmjax.diffusion.objectives.object_mask`: without it a 3-pixel agent is a rounding error
of the MSE, and the autoencoder drops it), plus ``kl_weight`` times the KL divergence to a
standard normal, both per value. After training, the latent means of held-out frames set the
folder's ``shift_factor`` and ``scaling_factor``, so that the latents a world model diffuses
have mean 0 and variance 1 (how SD's 0.18215 was chosen).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import shutil
import time
from typing import Mapping

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax

from wmjax import registry
from wmjax.codecs import VAECodec
from wmjax.config import ConfigError, complete_config
from wmjax.data.rlds import make_window
from wmjax.data.sources import ArrayRecordEpisodes, open_dataset
from wmjax.diffusion.objectives import object_mask
from wmjax.eval.metrics import frame_metrics
from wmjax.eval.video import frame_grid, write_png
from wmjax.frames import to_model, to_uint8
from wmjax.nn.vae import AutoencoderKL, VAEConfig, save_diffusers

log = logging.getLogger(__name__)

REPORT = "wmjax_codec.json"


@dataclasses.dataclass(frozen=True)
class CodecRecipe:
  """How a codec is fitted: the network (``widths``: one level each, downsampling by
  ``2 ** (len(widths) - 1)``; ``latent_channels``) and its training."""

  widths: tuple[int, ...] = (32, 64, 64)
  latent_channels: int = 4
  steps: int = 2000
  batch_size: int = 32
  learning_rate: float = 1e-3
  kl_weight: float = 1e-4
  object_weight: float = 20.0
  object_dilation: int = 1
  train_frames: int = 16384  # frames read from the training split, whole episodes at random
  eval_frames: int = 256  # from the evaluation split: the report and the latent statistics
  seed: int = 0

  def __post_init__(self):
    if not self.widths or min(self.widths) < 1:
      raise ValueError(f"widths must be one or more positive ints, got {self.widths}")
    for name in ("latent_channels", "steps", "batch_size", "train_frames", "eval_frames"):
      if getattr(self, name) < 1:
        raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
    if self.kl_weight < 0 or self.object_weight < 0 or self.object_dilation < 0:
      raise ValueError("kl_weight, object_weight and object_dilation must be >= 0")

  def network(self) -> VAEConfig:
    return VAEConfig(block_out_channels=tuple(self.widths), layers_per_block=1,
                     latent_channels=self.latent_channels,
                     norm_num_groups=math.gcd(32, *self.widths))


@dataclasses.dataclass(frozen=True)
class Frames:
  """Frames ``[N, H, W, 3]`` uint8 and their per-step extras ``{name: [N, ...]}``."""

  images: np.ndarray
  extras: Mapping[str, np.ndarray]


def read_frames(episodes: ArrayRecordEpisodes, resolution: tuple[int, int], limit: int,
                rng: np.random.Generator) -> Frames:
  """Every frame of episodes drawn at random (without replacement) until ``limit`` frames."""
  lengths = episodes.lengths()
  order = rng.permutation(np.flatnonzero(lengths))
  if not len(order):
    raise ValueError(f"{episodes.builder_dir} [{episodes.split}] has no episode to read frames from")
  images, extras, count = [], [], 0
  for index in order:
    episode = episodes.episode(int(index))
    window = make_window(episode, episode.first_step, len(episode), resolution, int(index),
                         episodes.spec.resize)
    images.append(window["frames"])
    extras.append({k: np.asarray(window[k]) for k in episode.extras})
    count += len(window["frames"])
    if count >= limit:
      break
  stacked = {k: np.concatenate([e[k] for e in extras])[:limit] for k in extras[0]}
  return Frames(np.concatenate(images)[:limit], stacked)


def codec_loss(module: AutoencoderKL, params, frames: jax.Array, rng: jax.Array,
               recipe: CodecRecipe) -> tuple[jax.Array, dict]:
  """The loss of a batch of frames ``[B, H, W, 3]`` in [-1, 1] (module doc) and its parts."""
  mean, logvar = module.apply(params, frames, method="encode")
  latents = mean + jnp.exp(0.5 * logvar) * jax.random.normal(rng, mean.shape)
  error = jnp.square(module.apply(params, latents, method="decode") - frames)
  weights = 1.0 + recipe.object_weight * object_mask(frames, recipe.object_dilation)
  reconstruction = jnp.mean(error * weights)
  kl = 0.5 * jnp.mean(jnp.square(mean) + jnp.exp(logvar) - 1.0 - logvar)
  return reconstruction + recipe.kl_weight * kl, {"reconstruction": reconstruction, "kl": kl,
                                                  "mse": jnp.mean(error)}


def _train_step(module: AutoencoderKL, optimizer: optax.GradientTransformation,
                recipe: CodecRecipe):
  @jax.jit
  def step(params, opt_state, frames, rng):
    grads, parts = jax.grad(lambda p: codec_loss(module, p, frames, rng, recipe),
                            has_aux=True)(params)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, parts

  return step


def _encode_decode(module: AutoencoderKL, params, images: np.ndarray, batch: int):
  """Latent means and reconstructions (uint8) of ``images [N, H, W, 3]`` uint8, ``batch``
  frames a call (an unscaled :class:`wmjax.codecs.VAECodec`)."""
  codec = VAECodec(module, params, scaling_factor=1.0, chunk=batch)
  means = codec.encode(to_model(images)[None])  # [1, N, h, w, c]: N mapped over in chunks
  return np.asarray(means)[0], to_uint8(np.asarray(codec.decode(means)))[0]


def _check_out(out: str) -> None:
  if os.path.exists(os.path.join(out, "config.json")):
    raise FileExistsError(f"{out} already holds a codec (config.json); name another folder")
  if os.path.exists(out) and (not os.path.isdir(out) or os.listdir(out)):
    raise FileExistsError(f"{out} exists and is not an empty folder; name another folder")


def train_codec(config: ml_collections.ConfigDict, out: str, recipe: CodecRecipe = CodecRecipe()
                ) -> dict:
  """Fit an AutoencoderKL to the frames of ``config.data`` (one dataset, read at its
  resolution) and write it to ``out`` as a diffusers folder with a report (``wmjax_codec.json``:
  the recipe, the losses, held-out pixel and task metrics of the reconstructions, the latent
  shape and the config overrides that train a world model on it) and ``reconstructions.png``
  (held-out frames above their reconstructions). ``out`` must be new or an empty folder; it is
  written as ``out.incomplete`` and renamed when whole. Returns the report."""
  config = complete_config(config)
  if config.data.mixture:
    raise ConfigError("train-codec reads one dataset; the config mixes several (data.mixture)")
  _check_out(out)
  rng = np.random.default_rng(recipe.seed)
  module = AutoencoderKL(recipe.network())
  frames, checks, task = _training_frames(config, recipe, module.config.downsample_factor, rng)
  began = time.time()
  params, history = fit_codec(module, frames.images, recipe, rng)
  means, recons = _encode_decode(module, params, checks.images, recipe.batch_size)
  # the folder's shift and scale give the latents a world model diffuses mean 0 and variance 1
  network = dataclasses.replace(module.config, shift_factor=float(means.mean()),
                                scaling_factor=float(1.0 / max(means.std(), 1e-6)))
  metrics = frame_metrics(recons[:, None], checks.images[:, None],
                          {k: v[:, None] for k, v in checks.extras.items()},
                          registry.frame_metrics_of(task))
  report = _report(recipe, network, out, frames, checks, task, metrics, history)
  report["seconds"] = round(time.time() - began, 1)
  _write_codec(out, network, params, report, checks.images, recons)
  return report


def _training_frames(config: ml_collections.ConfigDict, recipe: CodecRecipe, factor: int,
                     rng: np.random.Generator) -> tuple[Frames, Frames, str]:
  """(frames of the training split, held-out frames of the evaluation split, the dataset's name)
  of ``config.data`` at its resolution, which the codec's downsampling ``factor`` must divide."""
  dataset = open_dataset(config.data)
  train, held_out = dataset.split(config.data.train_split), dataset.split(config.data.eval_split)
  resolution = dataset.resolution(train.spec)
  if resolution[0] % factor or resolution[1] % factor:
    raise ValueError(f"frames {resolution[0]}x{resolution[1]} are not divisible by the codec's "
                     f"downsampling factor {factor} ({len(recipe.widths)} widths)")
  frames = read_frames(train, resolution, recipe.train_frames, rng)
  checks = read_frames(held_out, resolution, recipe.eval_frames, rng)
  log.info("codec: %d training frames of %s, %d held out", len(frames.images), train.spec.name,
           len(checks.images))
  return frames, checks, held_out.spec.name


def fit_codec(module: AutoencoderKL, images: np.ndarray, recipe: CodecRecipe,
              rng: np.random.Generator) -> tuple[dict, list[dict]]:
  """(parameters, history) of ``module`` fitted to frames ``images [N, H, W, 3]`` uint8 in
  ``recipe.steps`` steps of ``recipe.batch_size`` frames drawn with ``rng``; the history holds
  the loss parts at every twentieth of the steps. A non-finite loss stops it with an error."""
  key = jax.random.key(recipe.seed)
  params = jax.jit(module.init)(key, to_model(images[:1]))  # one program, not one per layer
  schedule = optax.warmup_cosine_decay_schedule(0.0, recipe.learning_rate,
                                                min(100, recipe.steps // 10 + 1), recipe.steps)
  optimizer = optax.chain(optax.clip_by_global_norm(1.0), optax.adamw(schedule))
  opt_state = optimizer.init(params)
  step = _train_step(module, optimizer, recipe)
  history, began = [], time.time()
  for i in range(recipe.steps):
    batch = images[rng.integers(0, len(images), recipe.batch_size)]
    params, opt_state, parts = step(params, opt_state, to_model(batch), jax.random.fold_in(key, i))
    if (i + 1) % max(1, recipe.steps // 20) == 0 or i + 1 == recipe.steps:
      parts = {k: float(v) for k, v in parts.items()}
      if not all(map(math.isfinite, parts.values())):
        raise FloatingPointError(f"codec training diverged at step {i + 1}: {parts}; "
                                 f"lower the learning rate")
      history.append(dict(step=i + 1, seconds=round(time.time() - began, 1), **parts))
      log.info("codec step %d: %s", i + 1, parts)
  return params, history


def _report(recipe: CodecRecipe, network: VAEConfig, out: str, frames: Frames, checks: Frames,
            task: str, metrics: Mapping[str, np.ndarray], history: list[dict]) -> dict:
  """The codec's ``wmjax_codec.json`` (see :func:`train_codec`)."""
  factor = network.downsample_factor
  h, w = frames.images.shape[1:3]
  latent_shape = (h // factor, w // factor, recipe.latent_channels)
  return {
      "recipe": dataclasses.asdict(recipe), "dataset": task,
      "frame_shape": [h, w, 3], "latent_shape": list(latent_shape),
      "scaling_factor": network.scaling_factor, "shift_factor": network.shift_factor,
      "held_out": {k: float(np.nanmean(v)) for k, v in metrics.items()},
      "held_out_frames": len(checks.images), "train_frames": len(frames.images),
      "history": history,
      "overrides": ["--config.codec.kind=vae", f"--config.codec.path={os.path.abspath(out)}",
                    f"--config.frame_shape=({latent_shape[0]},{latent_shape[1]},{latent_shape[2]})",
                    f"--config.model.in_channels={latent_shape[2]}",
                    "--config.sampling.clip_denoised=False", "--config.diffusion.object_weight=0.0"],
  }


def _write_codec(out: str, network: VAEConfig, params: dict, report: dict, images: np.ndarray,
                 recons: np.ndarray) -> None:
  """The diffusers folder, its report and ``reconstructions.png`` (up to 8 held-out ``images``
  above their ``recons``), written as ``out.incomplete`` and renamed to ``out`` when whole: a
  stopped fit leaves no codec."""
  tmp = out.rstrip("/") + ".incomplete"
  shutil.rmtree(tmp, ignore_errors=True)
  save_diffusers(tmp, network, params)
  with open(os.path.join(tmp, REPORT), "w") as f:
    json.dump(report, f, indent=2)
  shown = min(8, len(images))
  write_png(os.path.join(tmp, "reconstructions.png"), frame_grid([images[:shown], recons[:shown]]))
  if os.path.isdir(out):
    os.rmdir(out)  # empty (checked by _check_out)
  os.rename(tmp, out)
