"""Pre-encoding a dataset with a config's codec (IRASim's latents, ``wmjax data encode``)."""

from __future__ import annotations

import itertools
from typing import Sequence

import jax
import ml_collections
import numpy as np

from wmjax.codecs import make_codec
from wmjax.config import ConfigError, complete_config
from wmjax.data.latents import codec_description, encode_dataset
from wmjax.data.pipeline import member_configs
from wmjax.data.sources import open_dataset
from wmjax.frames import to_model


def encode_latents(config: ml_collections.ConfigDict, out: str,
                   splits: Sequence[str] | None = None, dataset: str | None = None,
                   seed: int = 0) -> str:
  """Encode the ``splits`` (default: the data's train and eval splits) of the config's dataset
  (``dataset`` names the member of a mixture) into ArrayRecord latents under ``out``; returns
  it. Train from them with ``data.latents_dir=OUT``."""
  config = complete_config(config)
  members = {m.dataset: m for m in member_configs(config.data)}
  if dataset is None and len(members) > 1:
    raise ConfigError(f"the config mixes {sorted(members)}; pick one with --dataset")
  if dataset is not None and dataset not in members:
    raise ConfigError(f"--dataset {dataset!r} is not in the config's data ({sorted(members)})")
  data = members[dataset] if dataset else next(iter(members.values()))
  codec = make_codec(config.codec)
  source = open_dataset(data)
  splits = list(splits) if splits else [data.train_split, data.eval_split]
  resolution = source.resolution(source.split(splits[0]).spec)
  keys = (jax.random.fold_in(jax.random.key(seed), i) for i in itertools.count())
  return encode_dataset(source.builder_dir, out, splits, source.specs, resolution,
                        lambda frames: np.asarray(codec.encode(to_model(frames), next(keys))),
                        codec_description(config.codec), source.train_stats().to_dict())
