"""Static float8 scales for a ``model.fp8_matmuls`` model (:mod:`wmjax.nn.float8`), calibrated on
windows of a split it trained on."""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import numpy as np

from wmjax.data.pipeline import member_configs
from wmjax.data.sources import ArrayRecordEpisodes, open_dataset
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


def with_float8_scales(model: LoadedModel, rng: jax.Array) -> tuple[LoadedModel, str | None]:
  """What an inference command runs -> ``(model, how its float8 inputs are scaled)``: a
  ``model.fp8_matmuls`` model calibrated on the training split of (the first dataset of) its
  config's data (:func:`calibrated_float8`), or, where that split cannot be read, as it is, with
  per-token scales and the reason; any other model as it is, with None."""
  if not model.config.model.fp8_matmuls:
    return model, None
  data = member_configs(model.config.data)[0]
  try:
    dataset = open_dataset(data)
    episodes = dataset.split(data.train_split)
  except (OSError, ValueError) as e:
    return model, (f"per-token float8 scales: the {data.train_split!r} split to calibrate on "
                   f"cannot be read ({e})")
  model = calibrated_float8(model, episodes, dataset.resolution(episodes.spec),
                            model.normalize_actions, rng)
  return model, f"static float8 scales from windows of the {data.train_split!r} split"
