"""The training loop behind ``wmjax train``.

Per step: next batch of this process's data shard -> global sharded arrays -> jitted train step.
Around it: a progress bar (rate, ETA), TensorBoard scalars and ``metrics.jsonl``, periodic
evaluation (validation loss and rollout PSNR on held-out windows, exact square-position error on
the gridworld) with a ground truth | prediction GIF, async checkpoints of state + data iterator +
config + action statistics, resume from the latest checkpoint, a clean stop on SIGTERM, and a
stop with a clear message on a NaN / inf loss that leaves the last good checkpoint intact.

Workdir layout: ``checkpoints/``, ``tensorboard/``, ``metrics.jsonl``, ``samples/*.gif``,
``config.json``, and at the end ``metrics.json`` and ``rollout.gif``.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import signal
import time
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from wmjax import parallel
from wmjax.codecs import Codec, PixelCodec
from wmjax.data.pipeline import training_pipeline
from wmjax.diffusion import diffusion_loss
from wmjax.eval.protocols import frame_metrics
from wmjax.eval.video import comparison, stack_rows, write_video
from wmjax.rollout import WorldModel, rollout
from wmjax.train.checkpoint import Checkpointer
from wmjax.train import memory
from wmjax.train.data import build_data, eval_windows
from wmjax.train.step import ShardedTrainer


class NonFiniteLossError(RuntimeError):
  """The loss became NaN or inf; training stopped without saving the bad state."""


# ----------------------------------------------------------------------------- evaluation


@functools.partial(jax.jit, static_argnums=(0, 5, 6))
def _validation_loss(world_model: WorldModel, params: Any, frames: jax.Array, actions: jax.Array,
                     rng: jax.Array, regime: str, num_context: int) -> jax.Array:
  def denoise(x, levels):
    return world_model.network.apply(params, x, world_model.process.model_time(levels), actions)
  return diffusion_loss(denoise, world_model.process, frames, rng, regime, num_context)[0]


def evaluate(world_model: WorldModel, params: Any, windows: dict[str, np.ndarray],
             config: ml_collections.ConfigDict, rng: jax.Array, codec: Codec,
             latents: bool = False) -> tuple[dict, np.ndarray, np.ndarray]:
  """Validation loss and rollout metrics on ``windows`` (RGB frames, or pre-encoded latents if
  ``latents``, whose pixel metrics then compare with the codec's reconstructions); returns
  (metrics, true RGB frames, predicted RGB frames)."""
  loss_rng, rollout_rng, encode_rng = jax.random.split(rng, 3)
  if latents:
    frames = jnp.asarray(windows["frames"])
    truth = np.asarray(codec.decode(frames))
  else:
    frames = codec.encode(jnp.asarray(windows["frames"]), encode_rng)
    truth = windows["frames"]  # already on the host
  actions = jnp.asarray(windows["actions"])
  c, h = config.rollout.context, config.rollout.horizon
  predicted = np.asarray(codec.decode(rollout(world_model, params, frames[:, :c],
                                              actions[:, c - 1:], rollout_rng, horizon=h)))
  val_loss = _validation_loss(world_model, params, frames, actions, loss_rng,
                              config.diffusion.regime, config.diffusion.num_context)
  extras = {k: windows[k][:, c:] for k in ("square_positions",) if k in windows}
  copy_last = np.broadcast_to(truth[:, c - 1:c], truth[:, c:].shape)
  result = {"val_loss": float(val_loss)}
  for prefix, candidate in (("rollout", predicted[:, c:]), ("copy_last", copy_last)):
    for name, values in frame_metrics(candidate, truth[:, c:], extras).items():
      result[f"{prefix}_{name}"] = float(np.nanmean(values))
  return result, truth, predicted


def write_samples(path: str, truth: np.ndarray, predicted: np.ndarray, count: int = 4) -> str:
  """Video (GIF or mp4) with one row per window: ground truth | prediction | difference."""
  rows = [comparison(truth[i], predicted[i]) for i in range(min(count, len(truth)))]
  return write_video(path, stack_rows(rows))


# ----------------------------------------------------------------------------- loop


def _batch_fingerprint(batch: dict[str, np.ndarray]) -> str:
  ids = np.stack([batch["episode"], batch["start"], batch["source"]], -1).astype(np.int64)
  return hashlib.sha1(ids.tobytes()).hexdigest()[:16]


class _StopFlag:
  """Set by SIGTERM: the loop saves a checkpoint and exits cleanly."""

  def __init__(self):
    self.requested = False
    self._previous = signal.signal(signal.SIGTERM, self._handle)

  def _handle(self, signum, frame):
    del signum, frame
    self.requested = True

  def restore(self):
    signal.signal(signal.SIGTERM, self._previous)


def train(config: ml_collections.ConfigDict, workdir: str) -> tuple[Any, dict]:
  """Train (or resume) in ``workdir``; returns the final train state and evaluation metrics."""
  from tensorboardX import SummaryWriter
  from tqdm import tqdm

  workdir = os.path.abspath(os.path.expanduser(workdir))
  os.makedirs(workdir, exist_ok=True)
  is_chief = jax.process_index() == 0
  data = build_data(config)
  mesh = parallel.make_mesh(config.mesh)
  shards = mesh.shape["data"] * mesh.shape["fsdp"]
  if config.batch_size % shards or config.batch_size % jax.process_count():
    raise ValueError(f"global batch_size {config.batch_size} is not divisible by the data-parallel "
                     f"size {shards} and the {jax.process_count()} processes")
  if is_chief:
    print(memory.describe(memory.estimate(config, jax.device_count())), flush=True)
  world_model = WorldModel.from_config(config)
  trainer = ShardedTrainer(world_model, config, mesh, tuple(config.frame_shape), config.data.frames)
  iterator = iter(training_pipeline(
      [m.train for m in data.members], [m.stats for m in data.members],
      weights=[m.weight for m in data.members],
      batch_size=config.batch_size // jax.process_count(),
      seed=config.seed, normalization=config.data.normalization,
      action_dim=config.model.action_dim, num_workers=config.data.num_workers))
  checkpoints = Checkpointer(os.path.join(workdir, "checkpoints"), config.train.max_checkpoints)
  config_dict, stats_dict = json.loads(config.to_json()), data.stats_dict()
  if is_chief:
    with open(os.path.join(workdir, "config.json"), "w") as f:
      f.write(config.to_json(indent=2))

  start = checkpoints.latest_step()
  if start is None:
    state, start = trainer.init(jax.random.key(config.seed)), 0
  else:
    state, _, _ = checkpoints.restore(start, trainer.abstract_state, iterator)
    print(f"resumed from step {start} in {checkpoints.directory}", flush=True)
  windows = eval_windows(data, config)
  writer = SummaryWriter(os.path.join(workdir, "tensorboard")) if is_chief else None
  log = open(os.path.join(workdir, "metrics.jsonl"), "a") if is_chief else None
  stop = _StopFlag()
  num_steps, train_cfg = config.train.num_steps, config.train
  # RGB batches -> latents on the device (unless they were pre-encoded)
  encode_frames = not data.latents and not isinstance(data.codec, PixelCodec)
  encode_key = jax.random.key(config.seed + 1)
  last_good = start
  step = start

  def save(step):
    nonlocal last_good
    checkpoints.save(step, state, iterator, config_dict, stats_dict)
    last_good = step

  def check_finite(loss, step):
    if not np.isfinite(loss):
      checkpoints.wait()
      raise NonFiniteLossError(
          f"loss is {loss} at step {step}; training stopped. The last good checkpoint (step "
          f"{last_good}) in {checkpoints.directory} is intact. Lower optim.learning_rate or "
          f"raise optim.grad_clip and resume.")

  try:
    bar = tqdm(total=num_steps, initial=start, disable=not is_chief, desc="train",
               dynamic_ncols=True)
    tick = time.perf_counter()
    while step < num_steps and not stop.requested:
      batch = next(iterator)
      global_batch = parallel.global_batch({k: batch[k] for k in ("frames", "actions")}, mesh)
      frames = global_batch["frames"]
      if encode_frames:  # the latents keep the batch's sharding
        frames = jax.device_put(data.codec.encode(frames, jax.random.fold_in(encode_key, step)),
                                frames.sharding)
      state, step_metrics = trainer.step(state, frames, global_batch["actions"])
      step += 1
      bar.update(1)
      if step % train_cfg.log_every == 0 or step % train_cfg.checkpoint_every == 0:
        scalars = {k: float(v) for k, v in step_metrics.items()}
        check_finite(scalars["loss"], step)
        now = time.perf_counter()
        scalars["samples_per_s"] = train_cfg.log_every * config.batch_size / (now - tick)
        tick = now
        bar.set_postfix(loss=f"{scalars['loss']:.4f}")
        if is_chief:
          for key, value in scalars.items():
            writer.add_scalar(f"train/{key}", value, step)
          log.write(json.dumps({"step": step, **scalars,
                                "batch": _batch_fingerprint(batch)}) + "\n")
          log.flush()
      if step % train_cfg.checkpoint_every == 0:
        save(step)
      if step % train_cfg.eval_every == 0 and step < num_steps:
        result, truth, predicted = evaluate(world_model, state.ema_params, windows, config,
                                            jax.random.key(step), data.codec, data.latents)
        if is_chief:
          for key, value in result.items():
            writer.add_scalar(f"eval/{key}", value, step)
          write_samples(os.path.join(workdir, "samples", f"step_{step:07d}.gif"), truth,
                        predicted)
          bar.write(f"step {step}: " + ", ".join(f"{k}={v:.4g}" for k, v in result.items()))
    if stop.requested:
      if step != last_good:
        save(step)
      checkpoints.wait()
      bar.write(f"SIGTERM: saved step {step} to {checkpoints.directory}; exiting")
      return state, {"step": step, "stopped": "SIGTERM"}
    if step != last_good:
      check_finite(float(step_metrics["loss"]), step)
      save(step)
    checkpoints.wait()
    bar.close()
    result, truth, predicted = evaluate(world_model, state.ema_params, windows, config,
                                        jax.random.key(num_steps), data.codec, data.latents)
    result["step"] = step
    if is_chief:
      write_samples(os.path.join(workdir, "rollout.gif"), truth, predicted)
      with open(os.path.join(workdir, "metrics.json"), "w") as f:
        json.dump(result, f, indent=2)
      for key, value in result.items():
        writer.add_scalar(f"eval/{key}", value, step)
    return state, result
  finally:
    stop.restore()
    checkpoints.close()
    if writer is not None:
      writer.close()
      log.close()
