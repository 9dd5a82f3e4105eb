"""Self-forcing: training windows whose last context frame the model generated itself.

A rollout feeds the model its own frames, which differ from the data's in ways a model trained
only on the data's frames never sees (a faded outline, a smeared edge), so the error of each
generated frame carries into the next. With ``diffusion.self_forcing = f > 0`` the data windows
hold one frame more than the model's (``data.frames = model.num_frames + 1``); for a fraction
``f`` of each batch the frame at the model window's last context position is replaced by the
one the model samples (EMA parameters, ``config.sampling``: the rollout's own sampler) from the
frames before it, and the loss still asks for the data's next frame. From train step
``diffusion.self_forcing_start`` on: before it every sample trains on the data's frames 1..N.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import ml_collections

from wmjax.model import WorldModel
from wmjax.rollout import sample_block_traceable

REGIMES = ("irasim", "autoregressive")  # the context frames are clean


def check_self_forcing(config: ml_collections.ConfigDict) -> None:
  """ValueError for a ``diffusion.self_forcing`` that the data, model or regime cannot serve."""
  fraction, diffusion = config.diffusion.self_forcing, config.diffusion
  if not fraction:
    return
  if diffusion.self_forcing_start < 0:
    raise ValueError(f"diffusion.self_forcing_start is a train step, >= 0; got "
                     f"{diffusion.self_forcing_start}")
  if not 0 < fraction <= 1:
    raise ValueError(f"diffusion.self_forcing is the fraction of a batch trained on a generated "
                     f"context frame, in (0, 1]; got {fraction}")
  if diffusion.regime not in REGIMES or diffusion.kind == "regression":
    raise ValueError(f"diffusion.self_forcing needs clean context frames to replace: "
                     f"diffusion.regime in {REGIMES} and a diffusion process, got regime "
                     f"{diffusion.regime!r}, kind {diffusion.kind!r}")
  if config.data.frames != config.model.num_frames + 1:
    raise ValueError(f"diffusion.self_forcing generates a context frame from the frames before "
                     f"it, so the data windows need one frame more than the model's: "
                     f"data.frames = model.num_frames + 1 = {config.model.num_frames + 1}, got "
                     f"data.frames={config.data.frames}")
  generated_count(config.batch_size, fraction)


def generated_count(batch: int, fraction: float) -> int:
  """The samples of a batch of ``batch`` given a generated frame; they are spread evenly over
  it (every ``batch // count``-th), so ``count`` must divide ``batch``."""
  count = round(fraction * batch)
  if count < 1 or batch % count:
    raise ValueError(f"diffusion.self_forcing={fraction} of a batch of {batch} gives {count} "
                     f"samples with a generated frame; it must be a whole divisor of the batch "
                     f"(e.g. {1 / batch:g}, {2 / batch:g}, 0.25, 0.5, 1)")
  return count


def model_frames(config: ml_collections.ConfigDict) -> int:
  """The frames of the windows the train step trains on: ``data.frames``, less the one the
  self-forced windows generate from."""
  return config.data.frames - (1 if config.diffusion.self_forcing else 0)


def self_forced_windows(world_model: WorldModel, params: Any, frames: jax.Array,
                        actions: jax.Array, fraction: float, num_context: int, rng: jax.Array
                        ) -> tuple[jax.Array, jax.Array]:
  """Model windows from data windows one frame longer.

  ``frames [B, N+1, H, W, C]``, ``actions [B, N, A]`` -> ``frames [B, N, ...]`` (the data's
  frames 1..N) and ``actions [B, N-1, A]``, where for ``round(fraction * B)`` evenly spread
  samples frame ``num_context`` of the data (the model window's last context frame) is sampled
  by the model with ``params`` from the ``num_context`` frames before it. Traceable; no
  gradient flows through the generated frames.
  """
  b, c = frames.shape[0], num_context
  count = generated_count(b, fraction)
  chosen = jnp.arange(count) * (b // count)
  generated = sample_block_traceable(
      world_model, params, frames[chosen, :c], actions[chosen, :c],
      jnp.ones((count, c), bool), rng)  # [count, 1, H, W, C]
  windows = frames[:, 1:].at[chosen, c - 1].set(jax.lax.stop_gradient(generated[:, 0]))
  return windows, actions[:, 1:]
