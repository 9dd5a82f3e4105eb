"""Reward functions for rollouts in a world model: ``reward(frames [B, T, H, W, 3], instruction)
-> [B]`` float32 (frames uint8 or in [-1, 1]; the instruction is a string or one per rollout).

* :class:`wmjax.eval.vlm.VLMJudge` — a VLM asked whether the task succeeded (WPE's reward);
* :class:`GoalImageDistance` — similarity of the last frame to a goal image (IRASim's real-robot
  planning value), as negative MSE;
* :class:`SuccessClassifier` — a small CNN trained on dataset frames and success labels, giving
  the probability that the last frame shows success;
* a task's named rewards (:mod:`wmjax.registry`), e.g. ``coverage``: Push-T goal coverage
  read from the last frame (:func:`wmjax.tasks.pusht.rewards.coverage`).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import serialization

from wmjax.eval.vlm import VLMJudge  # noqa: F401  (re-exported: the VLM reward)
from wmjax.frames import to_model
from wmjax import registry


def _last_frames(frames) -> jax.Array:
  frames = to_model(frames)
  if frames.ndim != 5 or frames.shape[-1] != 3:
    raise ValueError(f"rollouts must be [B, T, H, W, 3], got shape {tuple(frames.shape)}")
  return frames[:, -1]


@dataclasses.dataclass(frozen=True)
class GoalImageDistance:
  """``-MSE`` between each rollout's last frame and ``goal [H, W, 3]`` (both in [-1, 1])."""

  goal: np.ndarray

  def __call__(self, frames, instruction=None) -> np.ndarray:
    del instruction
    last = _last_frames(frames)
    goal = to_model(self.goal)
    if tuple(goal.shape) != tuple(last.shape[1:]):
      raise ValueError(f"goal image must be {tuple(last.shape[1:])}, got {tuple(goal.shape)}")
    return -np.asarray(jnp.mean((last - goal) ** 2, axis=(1, 2, 3)), np.float32)


# ----------------------------------------------------------------------------- success classifier


class SuccessCNN(nn.Module):
  """Frames ``[B, H, W, 3]`` in [-1, 1] -> success logits ``[B]``: strided 3x3 convolutions with
  GroupNorm and SiLU, global average pooling, a linear head."""

  widths: tuple[int, ...] = (32, 64, 64)

  @nn.compact
  def __call__(self, frames: jax.Array) -> jax.Array:
    x = frames
    for width in self.widths:
      x = nn.Conv(width, (3, 3), strides=2)(x)
      x = nn.silu(nn.GroupNorm(num_groups=8)(x))
    return nn.Dense(1)(x.mean((1, 2)))[:, 0]


@dataclasses.dataclass
class SuccessClassifier:
  """A trained :class:`SuccessCNN`; calling it gives the success probability of each rollout's
  last frame ``[B]``. ``label``: what its positive class means (kept with the weights)."""

  params: Any
  widths: tuple[int, ...] = (32, 64, 64)
  frame_shape: tuple[int, int, int] = (48, 48, 3)
  label: str = ""

  def probabilities(self, frames) -> np.ndarray:
    """Success probability of single frames ``[N, H, W, 3]``."""
    frames = to_model(frames)
    if tuple(frames.shape[1:]) != tuple(self.frame_shape):
      raise ValueError(f"the classifier takes {self.frame_shape} frames, got "
                       f"{tuple(frames.shape[1:])}")
    return np.asarray(jax.nn.sigmoid(_logits(SuccessCNN(self.widths), self.params, frames)))

  def __call__(self, frames, instruction=None) -> np.ndarray:
    del instruction
    return self.probabilities(_last_frames(frames)).astype(np.float32)

  def save(self, directory: str) -> str:
    """Write ``params.msgpack`` + ``classifier.json`` into ``directory``."""
    os.makedirs(directory, exist_ok=True)
    with open(os.path.join(directory, "params.msgpack"), "wb") as f:
      f.write(serialization.to_bytes(self.params))
    with open(os.path.join(directory, "classifier.json"), "w") as f:
      json.dump({"widths": list(self.widths), "frame_shape": list(self.frame_shape),
                 "label": self.label}, f, indent=2)
    return directory

  @classmethod
  def load(cls, directory: str) -> "SuccessClassifier":
    with open(os.path.join(directory, "classifier.json")) as f:
      meta = json.load(f)
    widths, shape = tuple(meta["widths"]), tuple(meta["frame_shape"])
    template = jax.eval_shape(SuccessCNN(widths).init, jax.random.key(0),
                              jnp.zeros((1,) + shape))
    with open(os.path.join(directory, "params.msgpack"), "rb") as f:
      params = serialization.from_bytes(template, f.read())
    return cls(params, widths, shape, meta.get("label", ""))


@functools.partial(jax.jit, static_argnums=0)
def _logits(module: SuccessCNN, params, frames):
  return module.apply(params, frames)


def train_success_classifier(frames, labels, *, steps: int = 500, batch_size: int = 64,
                             learning_rate: float = 1e-3, widths=(32, 64, 64), seed: int = 0,
                             label: str = "") -> tuple[SuccessClassifier, dict[str, float]]:
  """Fit a :class:`SuccessCNN` to ``frames [N, H, W, 3]`` (uint8 or [-1, 1]) and boolean
  ``labels [N]`` with class-balanced logistic loss and AdamW; returns the classifier and the
  final training loss / accuracy."""
  frames = np.asarray(frames)
  labels = np.asarray(labels).astype(np.float32).reshape(-1)
  if frames.ndim != 4 or len(frames) != len(labels) or len(frames) == 0:
    raise ValueError(f"need frames [N, H, W, 3] and labels [N], got {frames.shape} and "
                     f"{labels.shape}")
  positive = labels.mean()
  if positive in (0.0, 1.0):
    raise ValueError(f"labels must contain both classes, got a positive fraction of {positive}")
  weights = np.where(labels > 0, 0.5 / positive, 0.5 / (1 - positive)).astype(np.float32)
  module = SuccessCNN(tuple(widths))
  rng = np.random.default_rng(seed)
  params = jax.jit(module.init)(jax.random.key(seed), to_model(frames[:1]))
  optimizer = optax.adamw(learning_rate)
  opt_state = optimizer.init(params)

  @jax.jit
  def step(params, opt_state, x, y, w):
    def loss_fn(p):
      logits = module.apply(p, x)
      return jnp.mean(w * optax.sigmoid_binary_cross_entropy(logits, y)), logits
    (loss, logits), grads = jax.value_and_grad(loss_fn, has_aux=True)(params)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    accuracy = jnp.mean((logits > 0) == (y > 0.5))
    return optax.apply_updates(params, updates), opt_state, loss, accuracy

  for _ in range(steps):
    index = rng.integers(0, len(frames), min(batch_size, len(frames)))
    params, opt_state, loss, accuracy = step(params, opt_state, to_model(frames[index]),
                                             labels[index], weights[index])
  classifier = SuccessClassifier(params, tuple(widths), tuple(frames.shape[1:]), label)
  return classifier, {"loss": float(loss), "accuracy": float(accuracy)}


def labelled_frames(builder_dir: str, split: str, key: str, threshold: float, *,
                    max_frames: int | None = None, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
  """Frames ``[N, H, W, 3]`` uint8 of a dataset split with labels ``extras[key] >= threshold``
  ``[N]`` (e.g. Push-T ``coverage``), at most ``max_frames`` of them drawn uniformly."""
  from wmjax.data.rlds import decode_image
  from wmjax.data.sources import ArrayRecordEpisodes

  source = ArrayRecordEpisodes(builder_dir, split)
  frames, labels = [], []
  for index in range(len(source)):
    episode = source.episode(index)
    if key not in episode.extras:
      raise ValueError(f"the dataset's steps have no {key!r}; they have "
                       f"{sorted(episode.extras)}")
    frames += [decode_image(image, None) for image in episode.images]
    labels.append(np.asarray(episode.extras[key], np.float64) >= threshold)
  frames, labels = np.stack(frames), np.concatenate(labels)
  if max_frames is not None and len(frames) > max_frames:
    keep = np.sort(np.random.default_rng(seed).choice(len(frames), max_frames, replace=False))
    frames, labels = frames[keep], labels[keep]
  return frames, labels


def reward_from_spec(spec: str):
  """A task's reward by name (:func:`wmjax.registry.rewards`, e.g. ``coverage`` for
  Push-T), ``vlm`` (:meth:`VLMJudge.from_env`), ``classifier:DIR`` (a saved
  :class:`SuccessClassifier`) or ``goal:IMAGE`` (:class:`GoalImageDistance` to a PNG / JPG)."""
  name, _, argument = spec.partition(":")
  named = registry.rewards()
  if name in named and not argument:
    return named[name]
  if name == "vlm" and not argument:
    return VLMJudge.from_env()
  if name == "classifier" and argument:
    return SuccessClassifier.load(argument)
  if name == "goal" and argument:
    from PIL import Image
    return GoalImageDistance(np.asarray(Image.open(argument).convert("RGB")))
  raise ValueError(f"reward must be {', '.join(sorted(named))}, vlm, classifier:DIR or "
                   f"goal:IMAGE, got {spec!r}")
