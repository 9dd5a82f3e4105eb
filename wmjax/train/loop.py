"""The training loop behind ``wmjax train``.

Per step: next batch of this process's data shard -> global sharded arrays -> jitted train step.
Around it: a progress bar (rate, ETA), TensorBoard scalars and ``metrics.jsonl``, periodic
evaluation (validation loss and rollout PSNR on held-out windows, exact square-position error on
the gridworld) with a ground truth | prediction GIF, and async checkpoints of state + config +
action statistics (the data position is the step).

A run is never lost or silently changed:
- one trainer per workdir (``train.lock``, see :mod:`wmjax.train.workdir`); a workdir the run
  created is removed again if it stops before writing anything (a config or data error);
- resume from the newest checkpoint that reads back (a damaged newer one is moved aside with a
  warning), only with the config it was trained with up to the changes :mod:`wmjax.train.resume`
  accepts; ``config.json`` is written after the restore, ``metrics.jsonl`` cut back to its step;
- a checkpoint is saved only if the whole train state is finite; a NaN / inf loss or state stops
  with a message that names the last good checkpoint;
- a background save that fails stops training at the next step, with a one-line message;
- SIGTERM or Ctrl-C save a checkpoint and stop (``wmjax train`` exits 128 + the signal number).

Workdir layout: ``checkpoints/``, ``tensorboard/``, ``metrics.jsonl``, ``samples/*.gif``,
``config.json``, ``config_changes.jsonl`` (changes accepted on resume), and at the end
``metrics.json`` and ``rollout.gif``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import json
import logging
import os
import signal
import sys
import threading
import time
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from wmjax import parallel
from wmjax.codecs import Codec, PixelCodec
from wmjax.data.pipeline import training_pipeline
from wmjax.diffusion import LevelSampling, diffusion_loss
from wmjax.errors import CheckpointError, RunError
from wmjax.eval.metrics import frame_metrics
from wmjax.eval.video import comparison, stack_rows, write_video
from wmjax.model import WorldModel
from wmjax.registry import FrameMetrics, frame_metrics_of
from wmjax.rollout import rollout
from wmjax.tasks import with_task
from wmjax.train import fit, memory
from wmjax.train.checkpoint import Checkpointer, shapes_by_path
from wmjax.train.data import build_data, eval_windows
from wmjax.train.resume import check_resume
from wmjax.train.step import ShardedTrainer
from wmjax.train.workdir import (METRICS_LOG, WorkdirLock, make_workdir, record_config_changes,
                                 remove_empty_dirs, truncate_metrics_log)


LIBRARY_LOG = "train.log"  # orbax's and asyncio's warnings and errors during training


class NonFiniteLossError(RunError):
  """The loss or the train state became NaN or inf; training stopped without saving the bad
  state."""


# ----------------------------------------------------------------------------- evaluation


@functools.partial(jax.jit, static_argnums=(0, 5, 6, 7))
def _validation_loss(world_model: WorldModel, params: Any, frames: jax.Array, actions: jax.Array,
                     rng: jax.Array, regime: str, num_context: int,
                     level_sampling: LevelSampling) -> jax.Array:
  def denoise(x, levels):
    return world_model.network.apply(params, x, world_model.process.model_time(levels), actions)
  return diffusion_loss(denoise, world_model.process, frames, rng, regime, num_context,
                        level_sampling)[0]


def evaluate(world_model: WorldModel, params: Any, windows: dict[str, np.ndarray],
             config: ml_collections.ConfigDict, rng: jax.Array, codec: Codec,
             latents: bool = False, task: FrameMetrics | None = None
             ) -> tuple[dict, np.ndarray, np.ndarray]:
  """Validation loss and rollout metrics on ``windows`` (RGB frames, or pre-encoded latents if
  ``latents``, whose pixel metrics then compare with the codec's reconstructions), with the
  dataset's own metrics (``task``) from the windows' per-frame extras; returns (metrics, true RGB
  frames, predicted RGB frames)."""
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
                              config.diffusion.regime, config.diffusion.num_context,
                              LevelSampling.from_config(config.diffusion))
  num_frames = windows["frames"].shape[1]
  extras = {k: v[:, c:] for k, v in windows.items()
            if k not in ("frames", "actions") and np.ndim(v) >= 2 and np.shape(v)[1] == num_frames}
  copy_last = np.broadcast_to(truth[:, c - 1:c], truth[:, c:].shape)
  result = {"val_loss": float(val_loss)}
  for prefix, candidate in (("rollout", predicted[:, c:]), ("copy_last", copy_last)):
    for name, values in frame_metrics(candidate, truth[:, c:], extras, task).items():
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


@jax.jit
def _all_finite(state: Any) -> jax.Array:
  leaves = [x for x in jax.tree.leaves(state) if jnp.issubdtype(x.dtype, jnp.inexact)]
  return jnp.all(jnp.stack([jnp.isfinite(x).all() for x in leaves]))


class _QuietFileHandler(logging.FileHandler):
  """A log file that gives up silently when it cannot be written (the disk it is on may be the
  full one the run is reporting)."""

  def handleError(self, record):
    del record


@contextlib.contextmanager
def _library_logs_to(path: str, names=("absl", "asyncio")):
  """Send the warnings and errors that orbax (through absl logging) and asyncio log while the run
  trains to ``path`` instead of the console: a failed save logs a traceback from every thread it
  touched, hundreds of lines that would bury the one-line reason the run stopped."""
  handler = _QuietFileHandler(path, delay=True)
  handler.setLevel(logging.WARNING)
  handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
  loggers = [logging.getLogger(name) for name in names]
  previous = [logger.propagate for logger in loggers]
  for logger in loggers:
    logger.addHandler(handler)
    logger.propagate = False
  try:
    yield
  finally:
    for logger, propagate in zip(loggers, previous):
      logger.removeHandler(handler)
      logger.propagate = propagate
    handler.close()


class _StopFlag:
  """SIGTERM and Ctrl-C (SIGINT) ask the loop to save a checkpoint and stop after the current
  step; a second Ctrl-C stops at once, without saving."""

  SIGNALS = (signal.SIGTERM, signal.SIGINT)

  def __init__(self):
    self.signum: int | None = None
    self._previous = {}
    if threading.current_thread() is threading.main_thread():
      self._previous = {s: signal.signal(s, self._handle) for s in self.SIGNALS}

  def _handle(self, signum, frame):
    del frame
    if self.signum == signal.SIGINT and signum == signal.SIGINT:
      raise KeyboardInterrupt
    self.signum = signum
    if signum == signal.SIGINT:
      sys.stderr.write("\nCtrl-C: saving a checkpoint after this step, then stopping (press "
                       "Ctrl-C again to stop at once without saving)\n")

  @property
  def requested(self) -> bool:
    return self.signum is not None

  def restore(self):
    for signum, handler in self._previous.items():
      signal.signal(signum, handler)


def _resume(checkpoints: Checkpointer, trainer: ShardedTrainer, config: ml_collections.ConfigDict,
            workdir: str, allow: Sequence[str], is_chief: bool):
  """(state, step, accepted config changes) from the newest checkpoint that reads back, or
  None when there is none. A damaged newer checkpoint is moved to ``WORKDIR/damaged_checkpoints``
  (kept, never deleted) with a warning; a config that may not resume stops the run."""
  wanted = shapes_by_path(trainer.abstract_state)
  damaged = []

  def unreadable(step, error):
    damaged.append((step, error))
    print(f"WARNING: {error}", file=sys.stderr, flush=True)

  for step in reversed(checkpoints.all_steps()):
    try:
      saved = checkpoints.read_config(step)
      stored = checkpoints.stored_shapes(step)
    except CheckpointError as e:
      unreadable(step, e)
      continue
    changes, accepted_by = check_resume(step, saved, config, stored, wanted, allow)
    try:
      state = checkpoints.restore(step, trainer.abstract_state)
    except CheckpointError as e:
      unreadable(step, e)
      continue
    if damaged and jax.process_count() > 1:
      raise CheckpointError(f"{damaged[0][1]}. Checkpoint {step} is intact: move "
                            f"{checkpoints.directory}/{damaged[0][0]} (and any newer) aside and "
                            f"rerun to resume from it.")
    for bad, _ in damaged:
      where = checkpoints.set_aside(bad, os.path.join(workdir, "damaged_checkpoints"))
      print(f"WARNING: checkpoint {bad} is damaged and was moved to {where}; resuming from "
            f"checkpoint {step}, the newest intact one.", file=sys.stderr, flush=True)
    if changes and is_chief:
      record_config_changes(workdir, step, changes, accepted_by)
      print("config changes accepted on resume: " + ", ".join(
          f"{k} {old!r} -> {new!r}" for k, (old, new) in changes.items()), flush=True)
    return state, step
  if damaged:
    raise CheckpointError(
        "no checkpoint in " + checkpoints.directory + " can be read: " + "; ".join(
            str(e) for _, e in damaged) + ". Move the directory aside to start afresh.")
  return None


def train(config: ml_collections.ConfigDict, workdir: str, *,
          allow_config_change: Sequence[str] = ()) -> tuple[Any, dict]:
  """Train (or resume) in ``workdir``; returns the final train state and evaluation metrics
  (only ``step`` with ``train.eval_every=0``).

  The task ``config.task`` names is imported first (:func:`wmjax.tasks.with_task`). A resumed
  run must match the config of its checkpoint except for
  :data:`wmjax.train.resume.SAFE_ON_RESUME` and the keys (or sections) named in
  ``allow_config_change``; see :mod:`wmjax.train.resume`. Stopped by SIGTERM or Ctrl-C, it saves
  a checkpoint (if the state is finite) and returns ``{'step', 'stopped', 'signal'}`` as metrics.
  """
  config = with_task(config)
  workdir = os.path.abspath(os.path.expanduser(workdir))
  created = make_workdir(workdir)
  try:
    return _train_locked(config, workdir, tuple(allow_config_change))
  except BaseException:
    if created is not None:  # an early failure (config, data) leaves no empty workdir behind
      remove_empty_dirs(created)
    raise


def _train_locked(config: ml_collections.ConfigDict, workdir: str,
                  allow: tuple[str, ...]) -> tuple[Any, dict]:
  """:func:`_train` holding the workdir's lock, the libraries' logs sent to its log file."""
  lock = WorkdirLock(workdir) if jax.process_index() == 0 else None
  if lock is not None:
    lock.acquire()
  try:
    with _library_logs_to(os.path.join(workdir, LIBRARY_LOG)):
      return _train(config, workdir, allow)
  finally:
    if lock is not None:
      lock.release()


@dataclasses.dataclass
class _Setup:
  """What a run is built from, checked and compiled before any state exists."""

  config: ml_collections.ConfigDict  # as fitted to the device's memory (remat, accumulation)
  data: Any  # wmjax.train.data.TrainData
  trainer: ShardedTrainer  # with its mesh and the step compiled
  say: Any  # print on the chief process, nothing elsewhere

  @property
  def world_model(self) -> WorldModel:
    return self.trainer.world_model


def _set_up(config: ml_collections.ConfigDict, is_chief: bool) -> _Setup:
  """Phase 1: data, mesh and model checked against each other, and the step compiled and fitted
  to the device's memory (the analytic estimate is only a hint beside XLA's figure). The one
  mesh of the run is the trainer's."""
  data = build_data(config, evaluation=config.train.eval_every > 0)
  say = functools.partial(print, flush=True) if is_chief else lambda *_: None
  say(f"hint: analytic {memory.describe(memory.estimate(config, jax.device_count()))}")
  config, trainer, _ = fit.fit_for_training(config, log=say)
  parallel.check_batch_divisible(config.batch_size, trainer.mesh, processes=jax.process_count(),
                                 what="global batch_size")
  return _Setup(config, data, trainer, say)


class _RunLog:
  """The chief's outputs of a run in ``workdir``: ``config.json``, the metrics log (cut back to
  the step resumed from), TensorBoard events; other processes write nothing."""

  def __init__(self, workdir: str, config: ml_collections.ConfigDict, start: int,
               is_chief: bool):
    from tensorboardX import SummaryWriter
    self.workdir, self.is_chief = workdir, is_chief
    self.writer = self._log = None
    if not is_chief:
      return
    with open(os.path.join(workdir, "config.json"), "w") as f:
      f.write(config.to_json(indent=2))
    truncate_metrics_log(workdir, start)
    # events of an earlier attempt past the resumed step are hidden from TensorBoard
    self.writer = SummaryWriter(os.path.join(workdir, "tensorboard"), purge_step=start)
    self._log = open(os.path.join(workdir, METRICS_LOG), "a")

  def training(self, step: int, scalars: dict, batch: dict) -> None:
    if self.is_chief:
      for key, value in scalars.items():
        self.writer.add_scalar(f"train/{key}", value, step)
      self._log.write(json.dumps({"step": step, **scalars,
                                  "batch": _batch_fingerprint(batch)}) + "\n")
      self._log.flush()

  def evaluation(self, step: int, result: dict, truth, predicted, samples: str) -> None:
    if self.is_chief:
      for key, value in result.items():
        self.writer.add_scalar(f"eval/{key}", value, step)
      write_samples(samples, truth, predicted)

  def close(self) -> None:
    for handle in (self.writer, self._log):
      if handle is not None:
        handle.close()


def _stop_message(checkpoints: Checkpointer, config: ml_collections.ConfigDict,
                  problem: str) -> str:
  """Why training stopped, what is kept, and what to change before rerunning."""
  checkpoints.wait()
  kept = (f"The last good checkpoint (step {checkpoints.last_saved}) in "
          f"{checkpoints.directory} is intact" if checkpoints.last_saved is not None else
          f"No checkpoint was saved yet in {checkpoints.directory}")
  clip = config.optim.grad_clip
  return (f"{problem}; training stopped. {kept}. Lower optim.learning_rate (now "
          f"{config.optim.learning_rate:g}) or clip gradients harder (a smaller "
          f"optim.grad_clip: now {clip:g}{', 0 = off' if not clip else ''}) and rerun"
          + (" with --allow_config_change=optim" if checkpoints.last_saved is not None
             else "") + ".")


def _train(config: ml_collections.ConfigDict, workdir: str,
           allow: tuple[str, ...]) -> tuple[Any, dict]:
  """The phases of a run: set up (:func:`_set_up`), restore or initialise the state, the steps
  (logging, checkpoints, evaluation, a signal's stop), the final save and evaluation."""
  from tqdm import tqdm

  is_chief = jax.process_index() == 0
  run = _set_up(config, is_chief)
  config, data, world_model = run.config, run.data, run.world_model
  config_dict, stats_dict = json.loads(config.to_json()), data.stats_dict()
  num_steps, train_cfg = config.train.num_steps, config.train
  # RGB batches -> latents on the device (unless they were pre-encoded)
  encode_frames = not data.latents and not isinstance(data.codec, PixelCodec)
  encode_key = jax.random.key(config.seed + 1)
  checkpoints = Checkpointer(os.path.join(workdir, "checkpoints"), train_cfg.max_checkpoints)
  outputs = iterator = bar = None
  stop = _StopFlag()
  try:
    # phase 2: the state, restored or new
    resumed = _resume(checkpoints, run.trainer, config, workdir, allow, is_chief)
    if resumed is None:
      state, start = run.trainer.init(jax.random.key(config.seed)), 0
    else:
      state, start = resumed
      print(f"resumed from step {start} in {checkpoints.directory}", flush=True)
    # batch k is a function of k alone, so the data reads on from the step
    iterator = iter(training_pipeline(
        [m.train for m in data.members], [m.stats for m in data.members],
        weights=[m.weight for m in data.members],
        batch_size=config.batch_size // jax.process_count(),
        seed=config.seed, normalization=config.data.normalization,
        action_dim=config.model.action_dim, num_workers=config.data.num_workers, start=start))
    evaluating = train_cfg.eval_every > 0
    windows = eval_windows(data, config) if evaluating else None
    task = frame_metrics_of(data.members[0].spec.name)
    outputs = _RunLog(workdir, config, start, is_chief)
    step = start
    step_metrics = None

    def save(step):
      if not bool(_all_finite(state)):
        raise NonFiniteLossError(_stop_message(checkpoints, config, (
            f"the train state at step {step} holds NaN or inf values and was not saved")))
      checkpoints.save(step, state, config_dict, stats_dict)

    def check_finite(loss, step):
      if not np.isfinite(loss):
        raise NonFiniteLossError(_stop_message(checkpoints, config,
                                               f"loss is {loss} at step {step}"))

    def evaluate_now(step):
      result, truth, predicted = evaluate(world_model, state.ema_params, windows, config,
                                          jax.random.key(step), data.codec, data.latents, task)
      return result, truth, predicted

    # phase 3: the steps
    bar = tqdm(total=num_steps, initial=start, disable=not is_chief, desc="train",
               dynamic_ncols=True)
    tick = time.perf_counter()
    while step < num_steps and not stop.requested:
      try:
        batch = next(iterator)
      except Exception:
        if stop.requested:  # the signal reached the data workers too: save what there is
          break
        raise
      global_batch = parallel.global_batch({k: batch[k] for k in ("frames", "actions")},
                                           run.trainer.mesh)
      frames = global_batch["frames"]
      if encode_frames:  # the latents keep the batch's sharding
        frames = jax.device_put(data.codec.encode(frames, jax.random.fold_in(encode_key, step)),
                                frames.sharding)
      state, step_metrics = run.trainer.step(state, frames, global_batch["actions"])
      step += 1
      bar.update(1)
      checkpoints.poll()  # a background save that failed stops the run now
      if step % train_cfg.log_every == 0 or step % train_cfg.checkpoint_every == 0:
        scalars = {k: float(v) for k, v in step_metrics.items()}
        check_finite(scalars["loss"], step)
        now = time.perf_counter()
        scalars["samples_per_s"] = train_cfg.log_every * config.batch_size / (now - tick)
        tick = now
        bar.set_postfix(loss=f"{scalars['loss']:.4f}")
        outputs.training(step, scalars, batch)
      if step % train_cfg.checkpoint_every == 0:
        save(step)
      if evaluating and step % train_cfg.eval_every == 0 and step < num_steps:
        result, truth, predicted = evaluate_now(step)
        outputs.evaluation(step, result, truth, predicted,
                           os.path.join(workdir, "samples", f"step_{step:07d}.gif"))
        bar.write(f"step {step}: " + ", ".join(f"{k}={v:.4g}" for k, v in result.items()))
    if stop.requested and step < num_steps:
      name = signal.Signals(stop.signum).name
      checkpoints.wait()
      if step != checkpoints.last_saved and step > start:
        if step_metrics is not None:
          check_finite(float(step_metrics["loss"]), step)
        save(step)
        checkpoints.wait()
      saved = (f"saved step {step} to {checkpoints.directory}"
               if checkpoints.last_saved == step else "no step was trained, nothing to save")
      bar.write(f"{name}: {saved}; stopped before step {num_steps} (rerun the same command to "
                f"resume)")
      return state, {"step": step, "stopped": name, "signal": int(stop.signum)}
    # phase 4: the last save and evaluation
    checkpoints.wait()
    if step != checkpoints.last_saved:
      check_finite(float(step_metrics["loss"]), step)
      save(step)
    checkpoints.wait()
    bar.close()
    result = {}
    if evaluating:
      result, truth, predicted = evaluate_now(num_steps)
      outputs.evaluation(step, {}, truth, predicted, os.path.join(workdir, "rollout.gif"))
    result["step"] = step
    if is_chief:
      with open(os.path.join(workdir, "metrics.json"), "w") as f:
        json.dump(result, f, indent=2)
      for key, value in result.items():
        outputs.writer.add_scalar(f"eval/{key}", value, step)
    return state, result
  finally:
    stop.restore()
    failing = sys.exc_info()[0] is not None
    try:
      checkpoints.close()
    except CheckpointError:
      if not failing:
        raise
    finally:
      if bar is not None:
        bar.close()
      if iterator is not None and hasattr(iterator, "close"):
        iterator.close()
      if outputs is not None:
        outputs.close()
