"""Pre-encoded latents (IRASim encodes its datasets with the VAE once, before training).

``wmjax data encode`` runs every episode of a dataset's splits through the config's codec and
writes, per split, one ArrayRecord file of episodes (msgpack: ``latents`` float16
``[L, h, w, c]``, standardised ``actions`` ``[L, A]``, ``instruction``, per-step extras) plus
``wmjax_latents.json`` (dataset, its spec, resolution, latent shape, the codec, episode lengths and
the train split's action statistics). :class:`LatentEpisodes` reads them with the interface of
:class:`wmjax.data.sources.ArrayRecordEpisodes`, so windows, shuffling, sharding and
checkpointable iterators work unchanged; set ``config.data.latents_dir`` to train from them.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
from typing import Any, Callable, Mapping, Sequence

import grain
import ml_collections
import numpy as np
from array_record.python.array_record_module import ArrayRecordWriter
from flax import serialization

from wmjax.data import oxe
from wmjax.data.rlds import Episode, make_window
from wmjax.data.sources import ArrayRecordEpisodes, SpecArg, Splits
from wmjax.data.stats import ActionStats

METADATA = "wmjax_latents.json"


def _split_file(split: str) -> str:
  """``train[:95%]`` -> ``train___95__.array_record``."""
  return re.sub(r"[^\w.-]", "_", split) + ".array_record"


def codec_description(codec_config) -> dict:
  """What identifies a codec's latents (compared when training reads them)."""
  if codec_config is None:
    return {"kind": "pixel"}
  keys = ("kind", "path", "patch_size", "sample", "scaling_factor", "shift_factor")
  out = {k: codec_config.get(k) for k in keys if codec_config.get(k) is not None}
  if codec_config.get("random_vae"):  # no folder: the layout and widths are the weights
    out.pop("path", None)
    out.update(random_vae=codec_config.random_vae,
               random_vae_widths=list(codec_config.random_vae_widths))
  elif out.get("path"):
    out["path"] = os.path.abspath(os.path.expanduser(out["path"]))
  return out


def encode_dataset(builder_dir: str, out: str, splits: Sequence[str], spec: SpecArg,
                   resolution: tuple[int, int], encode: Callable[[np.ndarray], np.ndarray],
                   codec: dict, action_stats: dict) -> str:
  """Encode every episode of ``splits`` read with ``spec`` (see
  :class:`~wmjax.data.sources.ArrayRecordEpisodes`; episodes without its camera are left out)
  with ``encode`` (uint8 frames ``[L, H, W, 3]`` -> latents ``[L, h, w, c]``) into ``out``,
  which must not exist; written to a temporary directory first and renamed when complete."""
  if os.path.exists(out):
    raise FileExistsError(f"{out} exists; choose a new directory (latents are never overwritten)")
  tmp = out.rstrip("/") + ".incomplete"
  shutil.rmtree(tmp, ignore_errors=True)
  os.makedirs(tmp)
  metadata: dict[str, Any] = {"resolution": list(resolution), "codec": codec, "splits": {},
                              "action_stats": action_stats}
  for split in splits:
    episodes = ArrayRecordEpisodes(builder_dir, split, spec)
    metadata.update(dataset=episodes.spec.name, spec=episodes.spec.to_dict(),
                    builder_dir=os.fspath(builder_dir))
    writer = ArrayRecordWriter(os.path.join(tmp, _split_file(split)), "group_size:1")
    lengths = []
    for index in np.flatnonzero(episodes.lengths()):
      episode = episodes.episode(int(index))
      window = make_window(episode, 0, len(episode), resolution, int(index), episodes.spec.resize)
      latents = np.asarray(encode(window["frames"]), np.float16)
      record = {"latents": latents, "actions": episode.actions.astype(np.float32),
                "instruction": episode.instruction,
                "extras": {k: np.asarray(v) for k, v in episode.extras.items()}}
      writer.write(serialization.msgpack_serialize(record))
      lengths.append(len(episode))
      metadata["latent_shape"] = list(latents.shape[1:])
    writer.close()
    metadata["splits"][split] = {"episodes": len(lengths), "lengths": lengths}
  with open(os.path.join(tmp, METADATA), "w") as f:
    json.dump(metadata, f, indent=2)
  os.rename(tmp, out)
  return out


def read_metadata(latents_dir: str) -> dict:
  path = os.path.join(latents_dir, METADATA)
  if not os.path.isfile(path):
    raise FileNotFoundError(f"{latents_dir} holds no {METADATA}: not a `wmjax data encode` output")
  with open(path) as f:
    return json.load(f)


class LatentEpisodes:
  """Random access to the pre-encoded episodes of one split (picklable, for grain workers)."""

  def __init__(self, latents_dir: str, split: str):
    self.metadata = read_metadata(latents_dir)
    if split not in self.metadata["splits"]:
      raise ValueError(f"{latents_dir} has no split {split!r}; splits: "
                       f"{sorted(self.metadata['splits'])}")
    self.builder_dir, self.split = os.fspath(latents_dir), split
    self.spec = dataclasses.replace(oxe.DatasetSpec.from_dict(self.metadata["spec"]),
                                    resolution=tuple(self.metadata["resolution"]))
    self._lengths = np.asarray(self.metadata["splits"][split]["lengths"], np.int64)
    self._source = grain.sources.ArrayRecordDataSource(
        [os.path.join(latents_dir, _split_file(split))])

  def __len__(self) -> int:
    return len(self._lengths)

  def lengths(self) -> np.ndarray:
    return self._lengths

  def episode(self, index: int, start: int = 0, stop: int | None = None) -> Episode:
    """Episode ``index`` (steps ``[start, stop)``) with latents ``[L, h, w, c]`` as its images."""
    record = serialization.msgpack_restore(self._source[index])
    stop = len(record["latents"]) if stop is None else stop
    return Episode(images=np.asarray(record["latents"][start:stop]),
                   actions=np.asarray(record["actions"][start:stop]),
                   instruction=record["instruction"],
                   extras={k: np.asarray(v)[start:stop] for k, v in record["extras"].items()},
                   first_step=start)


def open_latent_splits(data: ml_collections.ConfigDict, codec: Mapping | None,
                       evaluation: bool = True) -> Splits:
  """The :class:`~wmjax.data.sources.Splits` of the latents in ``data.latents_dir``, which must
  have been encoded with ``codec`` (a ``config.codec``): their statistics and resolution are
  those of the dataset they were encoded from."""
  directory = os.path.expanduser(data.latents_dir)
  train = LatentEpisodes(directory, data.train_split)
  meta = train.metadata
  if meta["codec"] != codec_description(codec):
    raise ValueError(f"{directory} was encoded with codec {meta['codec']}, but config.codec is "
                     f"{codec_description(codec)}")
  held_out = LatentEpisodes(directory, data.eval_split) if evaluation else None
  return Splits(train, held_out, ActionStats.from_dict(meta["action_stats"]),
                tuple(meta["resolution"]), tuple(meta["latent_shape"]))
