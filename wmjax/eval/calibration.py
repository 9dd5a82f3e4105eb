"""Static float8 scales for a ``model.fp8_matmuls`` model (:mod:`wmjax.nn.float8`), calibrated on
windows of the split it trained on."""

from __future__ import annotations

import dataclasses

import jax

from wmjax.data.pipeline import member_configs
from wmjax.data.sources import ConfiguredDataset, open_dataset
from wmjax.eval.trajectories import Trajectories, windows_of
from wmjax.frames import to_model
from wmjax.model import LoadedModel


def with_float8_scales(model: LoadedModel, rng: jax.Array,
                       dataset: ConfiguredDataset | None = None, windows: int = 16
                       ) -> tuple[LoadedModel, str | None]:
  """What an inference command runs -> ``(model, how its float8 inputs are scaled)``.

  A ``model.fp8_matmuls`` model comes back with its float8 layers' input scales calibrated
  (:meth:`wmjax.model.WorldModel.calibrate_float8`) on the first ``windows`` windows of the
  network's length in the training split of (the first dataset of) its config's data (training
  data: the scales must not come from the frames an evaluation scores), ``dataset`` when the
  caller has it open already, encoded by the model's codec; the rollout's ``context`` frames of
  each window clean, the rest noised at the sampler's levels. Where that split cannot be read it
  comes back as it is, with per-token scales and the reason. Any other model comes back as it
  is, with None."""
  if not model.config.model.fp8_matmuls:
    return model, None
  data = member_configs(model.config.data)[0]
  try:
    dataset = dataset or open_dataset(data)
    episodes = dataset.split(data.train_split)
  except (OSError, ValueError) as e:
    return model, (f"per-token float8 scales: the {data.train_split!r} split to calibrate on "
                   f"cannot be read ({e})")
  length = model.world_model.network.num_frames
  found = windows_of(episodes, length, dataset.resolution(episodes.spec), windows)
  if not found:
    raise ValueError(f"float8 calibration needs windows of {length} frames (model.num_frames); "
                     f"no episode of the {data.train_split!r} split is that long")
  picked = Trajectories.stack(found, model.normalize_actions)
  encode_key, noise_key = jax.random.split(rng)
  frames = model.codec.encode(to_model(picked.frames), encode_key)
  params = model.world_model.calibrate_float8(model.params, frames, picked.actions, noise_key,
                                              context=model.config.rollout.context)
  return (dataclasses.replace(model, params=params),
          f"static float8 scales from windows of the {data.train_split!r} split")
