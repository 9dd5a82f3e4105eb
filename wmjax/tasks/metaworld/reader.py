"""The arm's state read off frames: a small CNN per camera view, fitted to simulator frames.

One :class:`ViewReaderCNN` per view of a frame (``[H, V*H, 3]``, square views side by side) reads
the end effector's pixel in the first view (``ee_px``, ``(col, row)``), the hand and the object
positions (``state``, metres: :data:`.simulator.STATE_SIZE`) and the success logit. Each view
reads the same targets on its own, so the two estimates of the hand's 3-D position can be set
against each other (:func:`cross_view_gap`: a world model whose views disagree imagines two
different arms); the fused estimate weights each view by the inverse of its error on held-out
frames, per target.

:func:`fit_reader` fits it to a dataset split's frames and the true values the simulator stored
with them (``observation/ee_px``, ``state``, ``success``) and reports its own error on another
split: the floor under every metric it reads off a world model's frames.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import time
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import serialization

from wmjax.frames import to_model
from wmjax.tasks.metaworld.metrics import split_views
from wmjax.tasks.metaworld.simulator import STATE_SIZE

TARGETS = 2 + STATE_SIZE  # ee_px (2) and state (6), regressed; success is the last output


class ViewReaderCNN(nn.Module):
  """One view ``[B, S, S, 3]`` in [-1, 1] -> ``[B, TARGETS + 1]``: standardised targets and the
  success logit. Strided 3x3 convolutions with GroupNorm and SiLU, then a dense layer over the
  flattened map (where things are matters: no global pooling)."""

  widths: tuple[int, ...] = (32, 64, 64)

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    for width in self.widths:
      x = nn.Conv(width, (3, 3), strides=2)(x)
      x = nn.silu(nn.GroupNorm(num_groups=8)(x))
    x = nn.silu(nn.Dense(128)(x.reshape(x.shape[0], -1)))
    return nn.Dense(TARGETS + 1)(x)


def _apply(module: ViewReaderCNN, params, views):
  """``params`` (one tree per view), ``views [V, B, S, S, 3]`` -> ``[V, B, TARGETS + 1]``. A loop
  over the views, not a vmap: vmapped kernels become a grouped convolution, 4x slower on a CPU."""
  return jnp.stack([module.apply(p, v) for p, v in zip(params, views)])


_apply_views = jax.jit(_apply, static_argnums=0)


@dataclasses.dataclass
class ArmReader:
  """A fitted reader: ``params`` (a tuple, one tree per view), the targets' ``mean`` /
  ``std`` ``[TARGETS]``, and ``weights [V, TARGETS]`` (each view's share of the fused estimate)."""

  params: Any
  mean: np.ndarray
  std: np.ndarray
  weights: np.ndarray
  image_size: int
  views: int
  widths: tuple[int, ...] = (32, 64, 64)

  def read(self, frames, batch: int = 512) -> dict[str, np.ndarray]:
    """``frames [N, S, V*S, 3]`` (uint8 or [-1, 1]) -> ``{'per_view' [N, V, TARGETS] (ee_px,
    state), 'success_per_view' [N, V], 'ee_px' [N, 2], 'state' [N, 6], 'success' [N]}`` (the
    last three fused over the views; success as a probability)."""
    frames = np.asarray(frames)
    expected = (self.image_size, self.views * self.image_size, 3)
    if frames.ndim != 4 or tuple(frames.shape[1:]) != expected:
      raise ValueError(f"the reader takes frames [N, {expected[0]}, {expected[1]}, 3], got "
                       f"{tuple(frames.shape)}")
    outs = []
    for first in range(0, len(frames), batch):
      views = np.moveaxis(split_views(to_model(frames[first:first + batch])), 1, 0)
      outs.append(np.asarray(_apply_views(ViewReaderCNN(self.widths), self.params,
                                          jnp.asarray(views))))
    out = np.moveaxis(np.concatenate(outs, 1), 0, 1)  # [N, V, TARGETS + 1]
    per_view = out[..., :TARGETS] * self.std + self.mean
    success = 1 / (1 + np.exp(-out[..., TARGETS]))
    fused = (per_view * self.weights).sum(1)
    return {"per_view": per_view, "success_per_view": success, "ee_px": fused[:, :2],
            "state": fused[:, 2:], "success": success.mean(1)}

  def save(self, directory: str) -> str:
    os.makedirs(directory, exist_ok=True)
    with open(os.path.join(directory, "params.msgpack"), "wb") as f:
      f.write(serialization.to_bytes(self.params))
    with open(os.path.join(directory, "reader.json"), "w") as f:
      json.dump({"mean": self.mean.tolist(), "std": self.std.tolist(),
                 "weights": self.weights.tolist(), "image_size": self.image_size,
                 "views": self.views, "widths": list(self.widths)}, f, indent=2)
    return directory

  @classmethod
  def load(cls, directory: str) -> "ArmReader":
    with open(os.path.join(directory, "reader.json")) as f:
      meta = json.load(f)
    template = jax.eval_shape(_init, tuple(meta["widths"]), meta["views"], meta["image_size"], 0)
    with open(os.path.join(directory, "params.msgpack"), "rb") as f:
      params = serialization.from_bytes(template, f.read())
    return cls(params, np.asarray(meta["mean"], np.float32), np.asarray(meta["std"], np.float32),
               np.asarray(meta["weights"], np.float32), meta["image_size"], meta["views"],
               tuple(meta["widths"]))


@functools.partial(jax.jit, static_argnums=(0, 1, 2))  # one program, not an op at a time
def _init(widths: tuple[int, ...], views: int, size: int, seed: int) -> tuple:
  """A fresh reader's parameters, one tree per view."""
  keys = jax.random.split(jax.random.key(seed), views)
  return tuple(ViewReaderCNN(widths).init(k, jnp.zeros((1, size, size, 3))) for k in keys)


def labelled_frames(builder_dir: str, split: str, max_frames: int | None = None, seed: int = 0
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """A MetaWorld split's frames ``[N, S, V*S, 3]`` uint8 with their targets ``[N, TARGETS]``
  (ee_px, state) and success ``[N]``; at most ``max_frames`` drawn uniformly."""
  from wmjax.data.rlds import decode_image
  from wmjax.data.sources import ArrayRecordEpisodes

  source = ArrayRecordEpisodes(builder_dir, split)
  frames, targets, success = [], [], []
  for index in range(len(source)):
    episode = source.episode(index)
    frames.append(np.stack([decode_image(image, None) for image in episode.images]))
    targets.append(np.concatenate([episode.extras["ee_px"], episode.extras["state"]], -1))
    success.append(np.asarray(episode.extras["success"], bool))
  frames, targets, success = (np.concatenate(a) for a in (frames, targets, success))
  if max_frames is not None and len(frames) > max_frames:
    keep = np.sort(np.random.default_rng(seed).choice(len(frames), max_frames, replace=False))
    frames, targets, success = frames[keep], targets[keep], success[keep]
  return frames, targets.astype(np.float32), success


def reader_errors(reader: ArmReader, frames, targets, success) -> dict[str, Any]:
  """The reader's own error on frames whose truth is known: per view and fused, the end
  effector's pixel error (px), the hand's and the object's position error (cm), and the
  success accuracy."""
  read = reader.read(frames)
  truth = np.asarray(targets, np.float64)
  out = {}
  for name, values, prob in [(f"view{v}", read["per_view"][:, v], read["success_per_view"][:, v])
                             for v in range(reader.views)] + [
                                 ("fused", np.concatenate([read["ee_px"], read["state"]], -1),
                                  read["success"])]:
    out[name] = {
        "ee_px_error": float(np.linalg.norm(values[:, :2] - truth[:, :2], axis=-1).mean()),
        "hand_error_cm": float(100 * np.linalg.norm(values[:, 2:5] - truth[:, 2:5], axis=-1).mean()),
        "object_error_cm": float(100 * np.linalg.norm(values[:, 5:8] - truth[:, 5:8],
                                                      axis=-1).mean()),
        "success_accuracy": float(((prob > 0.5) == np.asarray(success, bool)).mean()),
    }
  return out


def cross_view_gap(reader: ArmReader, frames) -> np.ndarray:
  """``[N]`` distance (cm) between the hand positions the first two views of ``frames`` show."""
  per_view = reader.read(frames)["per_view"]
  return 100 * np.linalg.norm(per_view[:, 0, 2:5] - per_view[:, 1, 2:5], axis=-1)


def degrade(views: jax.Array, rng: jax.Array, blur: float, noise: float) -> jax.Array:
  """Views ``[V, B, S, S, 3]`` in [-1, 1] as a generator might draw them: each image blended
  towards its Gaussian blur (sigma about 1 px: two passes of the binomial filter [1, 2, 1] / 4
  along each axis) by a weight drawn uniformly from [0, ``blur``], plus Gaussian noise of a
  standard deviation drawn uniformly from [0, ``noise``]; the same for every view of a frame."""
  blurred = views
  for _ in range(2):
    for axis in (2, 3):
      padded = jnp.concatenate([jnp.take(blurred, jnp.array([0]), axis), blurred,
                                jnp.take(blurred, jnp.array([-1]), axis)], axis)
      size = blurred.shape[axis]
      blurred = (jax.lax.slice_in_dim(padded, 0, size, axis=axis)
                 + 2 * jax.lax.slice_in_dim(padded, 1, size + 1, axis=axis)
                 + jax.lax.slice_in_dim(padded, 2, size + 2, axis=axis)) / 4
  mix_rng, std_rng, noise_rng = jax.random.split(rng, 3)
  per_frame = (1, views.shape[1], 1, 1, 1)
  mix = jax.random.uniform(mix_rng, per_frame, maxval=blur)
  std = jax.random.uniform(std_rng, per_frame, maxval=noise)
  degraded = views + mix * (blurred - views) + std * jax.random.normal(noise_rng, views.shape)
  return jnp.clip(degraded, -1.0, 1.0)


def fit_reader(frames, targets, success, *, validation, steps: int = 2000,
               batch_size: int = 64, learning_rate: float = 1e-3, widths=(32, 64, 64),
               blur: float = 0.0, noise: float = 0.0, seed: int = 0, log_every: int = 500
               ) -> tuple[ArmReader, dict[str, Any]]:
  """Fit one :class:`ViewReaderCNN` per view to ``frames [N, S, V*S, 3]``, ``targets [N,
  TARGETS]`` and ``success [N]`` (squared error on the standardised targets plus the success's
  class-balanced logistic loss); ``validation = (frames, targets, success)`` of another split
  sets the fusion weights and is reported (:func:`reader_errors`). ``blur`` and ``noise`` > 0
  train on frames degraded as a generator's are (:func:`degrade`), so that the reader reads a
  world model's softer frames as it reads the simulator's. Prints one line every ``log_every``
  steps."""
  if not (0.0 <= blur <= 1.0 and noise >= 0.0):
    raise ValueError(f"blur must lie in [0, 1] and noise be >= 0, got blur={blur}, noise={noise}")
  frames, targets = np.asarray(frames), np.asarray(targets, np.float32)
  success = np.asarray(success, np.float32)
  if frames.ndim != 4 or len(frames) != len(targets) or len(frames) != len(success):
    raise ValueError(f"need frames [N, S, V*S, 3], targets [N, {TARGETS}] and success [N], got "
                     f"{frames.shape}, {targets.shape}, {success.shape}")
  size, views = frames.shape[1], frames.shape[2] // frames.shape[1]
  mean, std = targets.mean(0), targets.std(0) + 1e-6
  positive = float(np.clip(success.mean(), 1e-3, 1 - 1e-3))
  balance = np.where(success > 0, 0.5 / positive, 0.5 / (1 - positive)).astype(np.float32)
  module = ViewReaderCNN(tuple(widths))
  params = _init(tuple(widths), views, size, seed)
  optimizer = optax.adamw(optax.cosine_decay_schedule(learning_rate, steps))
  opt_state = optimizer.init(params)

  @jax.jit
  def step(params, opt_state, x, y, s, w, rng):
    if blur or noise:
      x = degrade(x, rng, blur, noise)

    def loss_fn(p):
      out = _apply(module, p, x)  # [V, B, TARGETS + 1]
      regression = jnp.mean((out[..., :TARGETS] - y) ** 2)
      logistic = jnp.mean(w * optax.sigmoid_binary_cross_entropy(out[..., TARGETS], s))
      return regression + logistic
    loss, grads = jax.value_and_grad(loss_fn)(params)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, loss

  rng, key = np.random.default_rng(seed), jax.random.key(seed)
  start = time.monotonic()
  for i in range(steps):
    index = rng.integers(0, len(frames), batch_size)
    x = np.moveaxis(split_views(to_model(frames[index])), 1, 0)
    params, opt_state, loss = step(params, opt_state, jnp.asarray(x),
                                   jnp.asarray((targets[index] - mean) / std),
                                   jnp.asarray(success[index]), jnp.asarray(balance[index]),
                                   jax.random.fold_in(key, i))
    if (i + 1) % log_every == 0 or i + 1 == steps:
      print(f"reader step {i + 1}/{steps}: loss {float(loss):.4f}, "
            f"{time.monotonic() - start:.0f} s", flush=True)
  uniform = np.full((views, TARGETS), 1.0 / views, np.float32)
  reader = ArmReader(params, mean, std, uniform, size, views, tuple(widths))
  val_frames, val_targets, val_success = validation
  errors = (reader.read(val_frames)["per_view"] - np.asarray(val_targets)[:, None]) ** 2
  inverse = 1.0 / np.maximum(errors.mean(0), 1e-12)  # [V, TARGETS]
  reader.weights = (inverse / inverse.sum(0)).astype(np.float32)
  metrics = {"final_loss": float(loss), "train_frames": int(len(frames)), "blur": blur,
             "noise": noise,
             "validation_frames": int(len(val_frames)),
             "validation": reader_errors(reader, val_frames, val_targets, val_success)}
  return reader, metrics
