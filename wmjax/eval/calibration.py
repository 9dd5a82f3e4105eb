"""Static float8 scales for a ``model.fp8_matmuls`` model (:mod:`wmjax.nn.float8`), calibrated on
windows of a split it trained on."""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import numpy as np

from wmjax.data.sources import ArrayRecordEpisodes
from wmjax.eval.trajectories import Trajectories, windows_of
from wmjax.frames import to_model
from wmjax.model import LoadedModel


def calibrated_float8(model: LoadedModel, episodes: ArrayRecordEpisodes, resolution,
                      normalize: Callable[[np.ndarray], np.ndarray], rng: jax.Array,
                      windows: int = 16) -> LoadedModel:
  """``model`` with its float8 layers' input scales calibrated
  (:meth:`wmjax.model.WorldModel.calibrate_float8`) on the first ``windows`` windows of the
  network's length in ``episodes`` (of training data: the scales must not come from the frames
  an evaluation scores), encoded by the model's codec, their actions through ``normalize``; the
  rollout's ``context`` frames of each window clean, the rest noised at the sampler's levels."""
  length = model.world_model.network.num_frames
  found = windows_of(episodes, length, resolution, windows)
  if not found:
    raise ValueError(f"float8 calibration needs windows of {length} frames (model.num_frames); "
                     f"no episode of the calibration split is that long")
  picked = Trajectories.stack(found, normalize)
  encode_key, noise_key = jax.random.split(rng)
  frames = model.codec.encode(to_model(picked.frames), encode_key)
  params = model.world_model.calibrate_float8(model.params, frames, picked.actions, noise_key,
                                              context=model.config.rollout.context)
  return dataclasses.replace(model, params=params)
