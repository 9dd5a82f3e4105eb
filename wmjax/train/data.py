"""The data a training run reads: one dataset or a weighted mixture (``config.data.mixture``),
as RGB frames encoded by the codec on the device or as pre-encoded latents.

``config.data`` names one dataset (``dataset``, ``builder_dir`` or the generated gridworld,
``latents_dir``; ``spec`` / ``image_key`` / ``resize`` to read it, see
:func:`wmjax.data.oxe.specs_from_config`) or, with ``mixture``, several: ``mixture.<dataset>``
entries (schema :class:`wmjax.config.MixtureMember`: builder_dir, weight, latents_dir, splits,
spec, image_key, ...) whose fields left None inherit ``config.data`` (frames, strides,
resolution, resize, normalisation). Each member is normalised
with its own action statistics and its actions are zero-padded to ``model.action_dim``.
"""

from __future__ import annotations

import dataclasses
import os

import jax.numpy as jnp
import ml_collections
import numpy as np

from wmjax.codecs import Codec, make_codec
from wmjax.data import oxe
from wmjax.data.latents import LatentEpisodes, codec_description
from wmjax.data.pipeline import Normalize, WindowSource, frames_to_float
from wmjax.data.rlds import stack_steps
from wmjax.data.sources import member_configs, open_dataset
from wmjax.data.stats import ActionStats
from wmjax.eval.trajectories import Trajectories
from wmjax.frames import to_model, to_uint8


@dataclasses.dataclass
class Member:
  """One dataset of the run: its spec, action statistics, windows and mixture weight."""

  spec: oxe.DatasetSpec
  stats: ActionStats
  train: WindowSource
  eval: WindowSource | None  # None when the run does not evaluate (``train.eval_every=0``)
  weight: float


@dataclasses.dataclass
class TrainData:
  members: list[Member]
  codec: Codec  # RGB frames <-> the model's space
  latents: bool  # the windows hold pre-encoded latents (``latents_dir``), not RGB frames

  def stats_dict(self) -> dict:
    """Saved with every checkpoint: the first member's statistics (those ``wmjax rollout`` and
    ``WorldModelEnv`` normalise with), and every member's under ``mixture``."""
    out = self.members[0].stats.to_dict()
    if len(self.members) > 1:
      out["mixture"] = {m.spec.name: m.stats.to_dict() for m in self.members}
    return out


def _open_latents(data: ml_collections.ConfigDict, config: ml_collections.ConfigDict,
                  evaluation: bool):
  directory = os.path.expanduser(data.latents_dir)
  train_episodes = LatentEpisodes(directory, data.train_split)
  meta = train_episodes.metadata
  if meta["codec"] != codec_description(config.codec):
    raise ValueError(f"{directory} was encoded with codec {meta['codec']}, but config.codec is "
                     f"{codec_description(config.codec)}")
  if tuple(meta["latent_shape"]) != tuple(config.frame_shape):
    raise ValueError(f"{directory} holds latents of shape {tuple(meta['latent_shape'])}, but "
                     f"frame_shape is {tuple(config.frame_shape)}")
  eval_episodes = LatentEpisodes(directory, data.eval_split) if evaluation else None
  return (train_episodes, eval_episodes, ActionStats.from_dict(meta["action_stats"]),
          tuple(meta["resolution"]))


def _open_frames(data: ml_collections.ConfigDict, config: ml_collections.ConfigDict,
                 codec: Codec, evaluation: bool):
  dataset = open_dataset(data)
  train_episodes = dataset.split(data.train_split)
  eval_episodes = dataset.split(data.eval_split) if evaluation else None
  resolution = dataset.resolution(train_episodes.spec)
  if tuple(config.frame_shape) != codec.latent_shape(resolution + (3,)):
    raise ValueError(f"frame_shape {tuple(config.frame_shape)} does not match what the codec "
                     f"({config.codec.kind}) makes of "
                     f"{data.dataset}'s {resolution + (3,)} frames: "
                     f"{codec.latent_shape(resolution + (3,))}")
  return train_episodes, eval_episodes, dataset.train_stats(), resolution


def build_data(config: ml_collections.ConfigDict, evaluation: bool = True) -> TrainData:
  """Window sources and action statistics of every member, checked against the model before
  anything compiles; without ``evaluation`` the evaluation splits are not opened (a run with
  ``train.eval_every=0`` needs none)."""
  codec = make_codec(config.codec)
  frames = config.data.frames
  if frames > config.model.num_frames:
    raise ValueError(f"data.frames={frames} exceeds model.num_frames={config.model.num_frames}")
  members, kinds = [], set()
  for data in member_configs(config.data):
    latents = bool(data.latents_dir)
    kinds.add(latents)
    train_episodes, eval_episodes, stats, resolution = (
        _open_latents(data, config, evaluation) if latents
        else _open_frames(data, config, codec, evaluation))
    spec = train_episodes.spec
    # a mixture zero-pads smaller action spaces; a single dataset must match exactly
    mixture = bool(config.data.mixture)
    if spec.action_dim > config.model.action_dim or (
        not mixture and spec.action_dim != config.model.action_dim):
      raise ValueError(f"{spec.name} has {spec.action_dim}-dim actions but the model expects "
                       f"model.action_dim={config.model.action_dim}")
    members.append(Member(spec, stats,
                          WindowSource(train_episodes, frames, data.train_stride, resolution),
                          WindowSource(eval_episodes, frames, data.eval_stride, resolution)
                          if evaluation else None,
                          float(data.get("weight", 1.0))))  # a mixture member's
  if len(kinds) > 1:
    raise ValueError("a mixture must be all pre-encoded latents or all frames")
  return TrainData(members, codec, kinds.pop())


def _held_out_windows(data: TrainData, config: ml_collections.ConfigDict
                      ) -> dict[str, np.ndarray]:
  """``train.eval_windows`` held-out windows (shared out among the members), normalised and
  stacked, their frames as read (uint8 RGB or pre-encoded latents)."""
  total = config.train.eval_windows
  windows = []
  for i, member in enumerate(data.members):
    count = min(len(member.eval), -(-total // len(data.members)))
    normalize = Normalize(member.stats, config.data.normalization, config.model.action_dim, i,
                          keep_extras=len(data.members) == 1)
    windows += [normalize(member.eval[k]) for k in range(count)]
  return stack_steps(windows[:total])


def eval_windows(data: TrainData, config: ml_collections.ConfigDict) -> dict[str, np.ndarray]:
  """The fixed held-out windows evaluated during training, normalised and batched, their frames
  float32 (RGB in [-1, 1] or latents)."""
  return frames_to_float(_held_out_windows(data, config))


def eval_trajectories(data: TrainData, config: ml_collections.ConfigDict) -> Trajectories:
  """The windows of :func:`eval_windows` as trajectories to roll out
  (:func:`wmjax.eval.rollouts.run_rollouts`): uint8 RGB frames ``[E, F, H, W, 3]``, normalised
  actions ``[E, F-1, A]`` and the per-frame extras; pre-encoded latents are kept as the
  trajectories' latents (float32) and decoded by the codec for their RGB frames."""
  windows = _held_out_windows(data, config)
  frames, latents = windows["frames"], None
  if data.latents:
    latents = to_model(frames)
    frames = to_uint8(data.codec.decode(jnp.asarray(latents)))
  count, length = frames.shape[:2]
  extras = {k: v for k, v in windows.items() if k not in ("frames", "actions")
            and np.ndim(v) >= 2 and np.shape(v)[1] == length}
  return Trajectories(frames, windows["actions"], np.full(count, length), extras,
                      windows["episode"], windows["start"], latents)
