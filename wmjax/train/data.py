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

import jax.numpy as jnp
import ml_collections
import numpy as np

from wmjax.codecs import Codec, make_codec
from wmjax.data.pipeline import Member, Normalize, frames_to_float, open_members
from wmjax.data.rlds import stack_steps
from wmjax.eval.trajectories import Trajectories
from wmjax.frames import to_model, to_uint8
from wmjax.train.self_forcing import check_self_forcing, model_frames


@dataclasses.dataclass
class TrainData:
  members: list[Member]
  codec: Codec  # RGB frames <-> the model's space

  @property
  def latents(self) -> bool:
    """The windows hold pre-encoded latents (``latents_dir``), not RGB frames."""
    return self.members[0].latents

  def stats_dict(self) -> dict:
    """Saved with every checkpoint: the first member's statistics (those ``wmjax rollout`` and
    ``WorldModelEnv`` normalise with), and every member's under ``mixture``."""
    out = self.members[0].stats.to_dict()
    if len(self.members) > 1:
      out["mixture"] = {m.spec.name: m.stats.to_dict() for m in self.members}
    return out


def _check_member(member: Member, config: ml_collections.ConfigDict, codec: Codec) -> None:
  """The frames and actions of a dataset against the model's ``frame_shape`` and
  ``action_dim``."""
  frame_shape, spec = tuple(config.frame_shape), member.spec
  if member.latents and member.frame_shape != frame_shape:
    raise ValueError(f"{member.train.episodes.builder_dir} holds latents of shape "
                     f"{member.frame_shape}, but frame_shape is {frame_shape}")
  if not member.latents and frame_shape != codec.latent_shape(member.frame_shape):
    raise ValueError(f"frame_shape {frame_shape} does not match what the codec "
                     f"({config.codec.kind}) makes of {spec.name}'s {member.frame_shape} frames: "
                     f"{codec.latent_shape(member.frame_shape)}")
  # a mixture zero-pads smaller action spaces; a single dataset must match exactly
  if spec.action_dim > config.model.action_dim or (
      not config.data.mixture and spec.action_dim != config.model.action_dim):
    raise ValueError(f"{spec.name} has {spec.action_dim}-dim actions but the model expects "
                     f"model.action_dim={config.model.action_dim}")


def build_data(config: ml_collections.ConfigDict, evaluation: bool = True) -> TrainData:
  """Window sources and action statistics of every member
  (:func:`wmjax.data.pipeline.open_members`), checked against the model before anything
  compiles; without ``evaluation`` the evaluation splits are not opened (a run with
  ``train.eval_every=0`` needs none)."""
  codec = make_codec(config.codec)
  if config.diffusion.object_weight and config.codec.kind == "vae":
    raise ValueError("diffusion.object_weight weighs the loss where a value stands apart from its "
                     "frame's median, which in a VAE's latents is nearly every value; set "
                     "diffusion.object_weight=0 with codec.kind='vae'")
  check_self_forcing(config)
  if model_frames(config) > config.model.num_frames:
    raise ValueError(f"data.frames={config.data.frames} exceeds "
                     f"model.num_frames={config.model.num_frames}")
  members = open_members(config.data, config.codec, evaluation)
  for member in members:
    _check_member(member, config, codec)
  return TrainData(members, codec)


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
