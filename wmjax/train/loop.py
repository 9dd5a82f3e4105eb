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
from wmjax.codecs import PixelCodec
from wmjax.config import complete_config
from wmjax.data.pipeline import training_pipeline
from wmjax.diffusion import LevelSampling, diffusion_loss
from wmjax.errors import CheckpointError, RunError
from wmjax.progress import clock, plain
from wmjax.eval.rollouts import run_rollouts
from wmjax.eval.trajectories import Trajectories
from wmjax.eval.video import comparison, stack_rows, write_video
from wmjax.frames import to_model
from wmjax.model import LoadedModel, WorldModel, load_model
from wmjax.nn.dit import layers_scanned, relayout_layers
from wmjax.registry import frame_metrics_of
from wmjax.train.checkpoint import Checkpointer, shapes_by_path
from wmjax.train.context import TrainContext, set_up
from wmjax.train.data import eval_trajectories
from wmjax.train.resume import ConfigChangeError, check_resume, config_changes
from wmjax.train.self_forcing import model_frames
from wmjax.train.step import ShardedTrainer
from wmjax.train.workdir import (METRICS_LOG, claimed, record_config_changes,
                                 truncate_metrics_log)

LIBRARY_LOG = "train.log"  # orbax's and asyncio's warnings and errors during training


def progress_line(step: int, num_steps: int, start: int, loss: float, samples_per_s: float,
                  elapsed: float) -> str:
  """One line of training progress for a log file: step, loss, speed, elapsed time and the time
  left at the speed of the steps run since ``start`` (where this run began or resumed)."""
  left = (num_steps - step) * elapsed / max(step - start, 1)
  return (f"step {step}/{num_steps}: loss {loss:.4f}, {samples_per_s:.1f} samples/s, elapsed "
          f"{clock(elapsed)}, ETA {clock(left)}")


class NonFiniteLossError(RunError):
  """The loss or the train state became NaN or inf; training stopped without saving the bad
  state."""


# ----------------------------------------------------------------------------- evaluation


@functools.partial(jax.jit, static_argnums=(0, 5, 6, 7))
def _loss(world_model: WorldModel, params: Any, frames: jax.Array, actions: jax.Array,
          rng: jax.Array, regime: str, num_context: int, level_sampling: LevelSampling
          ) -> jax.Array:
  def denoise(x, levels):
    return world_model.network.apply(params, x, world_model.process.model_time(levels), actions)
  return diffusion_loss(denoise, world_model.process, frames, rng, regime, num_context,
                        level_sampling)[0]


def validation_loss(context: TrainContext, params: Any, trajectories: Trajectories,
                    rng: jax.Array, encode_rng: jax.Array) -> float:
  """The training loss of ``params`` on held-out ``trajectories`` of the training length (their
  frames in the model's space: encoded by the codec with ``encode_rng``, or their pre-encoded
  latents; the last ``model.num_frames`` where self-forced windows hold one more), its noise
  drawn from ``rng``."""
  config, codec = context.config, context.data.codec
  frames = (jnp.asarray(trajectories.latents) if trajectories.latents is not None
            else codec.encode(to_model(trajectories.frames, jnp), encode_rng))
  n = model_frames(config)
  frames, actions = frames[:, -n:], jnp.asarray(trajectories.actions)[:, frames.shape[1] - n:]
  return float(_loss(context.world_model, params, frames, actions,
                     rng, config.diffusion.regime, config.diffusion.num_context,
                     LevelSampling.from_config(config.diffusion)))


def evaluate(context: TrainContext, params: Any, trajectories: Trajectories, rng: jax.Array,
             step: int) -> tuple[dict, list]:
  """Validation loss and rollout metrics of ``params`` (at train ``step``) on ``trajectories``:
  :func:`wmjax.eval.rollouts.run_rollouts` from ``rollout.context`` frames in blocks of
  ``rollout.horizon``, the model and the copy-last-frame baseline scored with the dataset's own
  metrics, each averaged over the generated frames -> (metrics, up to 4 (truth, prediction)
  uint8 videos ``[F, H, W, 3]``)."""
  config, data = context.config, context.data
  loss_rng, rollout_rng, encode_rng = jax.random.split(rng, 3)
  model = LoadedModel(config, context.world_model, params, data.members[0].stats, step,
                      data.codec)
  outcome = run_rollouts(model, trajectories, first=0, context=config.rollout.context,
                         horizon=config.rollout.horizon, rng=rollout_rng,
                         batch_size=len(trajectories), keep_videos=4,
                         task=frame_metrics_of(data.members[0].spec.name))
  result = {"val_loss": validation_loss(context, params, trajectories, loss_rng, encode_rng)}
  for prefix, per_frame in (("rollout", outcome.model), ("copy_last", outcome.copy_last)):
    result.update({f"{prefix}_{name}": float(np.nanmean(values))
                   for name, values in per_frame.items()})
  return result, outcome.videos


def write_samples(path: str, videos: list[tuple[np.ndarray, np.ndarray]]) -> str:
  """Video (GIF or mp4) with one row per (truth, prediction) pair: ground truth | prediction |
  difference."""
  return write_video(path, stack_rows([comparison(truth, predicted)
                                       for truth, predicted in videos]))


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
  """(state, step) from the newest checkpoint that reads back
  (:meth:`~wmjax.train.checkpoint.Checkpointer.restore_newest`, damaged ones set aside in
  ``WORKDIR/damaged_checkpoints``), or None when there is none; a config that may not resume
  stops the run (:func:`wmjax.train.resume.check_resume`), and the changes it accepts are
  recorded."""

  def check(step, saved, stored):
    # layers saved in the other layout (model.scan_layers) are read as saved, then converted
    scanned = layers_scanned(stored)
    as_saved = (trainer.abstract_state if scanned in (None, config.model.scan_layers)
                else relayout_layers(trainer.abstract_state, scanned))
    return check_resume(step, saved, config, stored, shapes_by_path(as_saved), allow), as_saved

  restored = checkpoints.restore_newest(check, os.path.join(workdir, "damaged_checkpoints"))
  if restored is None:
    return None
  state, step, (changes, accepted_by) = restored
  if "model.scan_layers" in changes:
    state = jax.device_put(relayout_layers(state, config.model.scan_layers),
                           trainer.state_shardings)
  if changes and is_chief:
    record_config_changes(workdir, step, changes, accepted_by)
    print("config changes accepted on resume: " + ", ".join(
        f"{k} {old!r} -> {new!r}" for k, (old, new) in changes.items()), flush=True)
  return state, step


# model keys that change how the network computes or trains, not the function its weights are
_HOW_IT_COMPUTES = ("model.remat", "model.scan_layers", "model.dtype", "model.attention_impl",
                    "model.action_dropout", "model.fp8_matmuls")


def initial_weights(config: ml_collections.ConfigDict) -> Any:
  """The EMA weights of the newest checkpoint in ``config.train.init_from``, laid out as this
  config's layers are: where a new run starts. A :class:`ConfigChangeError` when the two model
  sections differ in anything but :data:`_HOW_IT_COMPUTES` (the weights would compute another
  function, or not fit)."""
  source = config.train.init_from
  loaded = load_model(source, overrides=[f"model.scan_layers={config.model.scan_layers}",
                                         "codec.kind='pixel'"])  # the weights alone
  differing = {key: change for key, change in config_changes(
      {"model": loaded.config.model.to_dict()}, {"model": config.model.to_dict()}).items()
               if key not in _HOW_IT_COMPUTES}
  if differing:
    raise ConfigChangeError(
        f"train.init_from={source!r}: its model differs from this config's in " + ", ".join(
            f"{key} ({old!r} there, {new!r} here)" for key, (old, new) in differing.items())
        + "; set them as it has them (--config.model.KEY=VALUE): its weights compute another "
        "function, or do not fit, in this model")
  print(f"parameters from step {loaded.step} of {source}", flush=True)
  return loaded.params


def train(config: ml_collections.ConfigDict, workdir: str, *,
          allow_config_change: Sequence[str] = ()) -> tuple[Any, dict]:
  """Train (or resume) in ``workdir``; returns the final train state and evaluation metrics
  (only ``step`` with ``train.eval_every=0``).

  The config is completed first, which imports the task ``config.task`` names
  (:func:`wmjax.config.complete_config`). A resumed
  run must match the config of its checkpoint except for
  :data:`wmjax.train.resume.SAFE_ON_RESUME` and the keys (or sections) named in
  ``allow_config_change``; see :mod:`wmjax.train.resume`. Stopped by SIGTERM or Ctrl-C, it saves
  a checkpoint (if the state is finite) and returns ``{'step', 'stopped', 'signal'}`` as metrics.
  """
  config = complete_config(config)
  with claimed(workdir, lock=jax.process_index() == 0) as workdir:
    with _library_logs_to(os.path.join(workdir, LIBRARY_LOG)):
      return _train(config, workdir, tuple(allow_config_change))


def _summary_writer(logdir: str, purge_step: int):
  """tensorboardX's ``SummaryWriter``, imported without PyTorch: tensorboardX imports ``torch``
  where it is installed, only to recognise its tensors (1.6 s of every training start on a 2-core
  CPU), and the run logs Python floats."""
  hide_torch = "torch" not in sys.modules
  if hide_torch:
    sys.modules["torch"] = None  # `import torch` raises ImportError, which tensorboardX handles
  try:
    from tensorboardX import SummaryWriter
  finally:
    if hide_torch:
      del sys.modules["torch"]
  return SummaryWriter(logdir, purge_step=purge_step)


class _RunLog:
  """The chief's outputs of a run in ``workdir``: ``config.json``, the metrics log (cut back to
  the step resumed from), TensorBoard events; other processes write nothing."""

  def __init__(self, workdir: str, config: ml_collections.ConfigDict, start: int,
               is_chief: bool):
    self.workdir, self.is_chief = workdir, is_chief
    self.writer = self._log = None
    if not is_chief:
      return
    with open(os.path.join(workdir, "config.json"), "w") as f:
      f.write(config.to_json(indent=2))
    truncate_metrics_log(workdir, start)
    # events of an earlier attempt past the resumed step are hidden from TensorBoard
    self.writer = _summary_writer(os.path.join(workdir, "tensorboard"), purge_step=start)
    self._log = open(os.path.join(workdir, METRICS_LOG), "a")

  def training(self, step: int, scalars: dict, batch: dict) -> None:
    if self.is_chief:
      for key, value in scalars.items():
        self.writer.add_scalar(f"train/{key}", value, step)
      self._log.write(json.dumps({"step": step, **scalars,
                                  "batch": _batch_fingerprint(batch)}) + "\n")
      self._log.flush()

  def evaluation(self, step: int, result: dict, videos: list, samples: str) -> None:
    if self.is_chief:
      for key, value in result.items():
        self.writer.add_scalar(f"eval/{key}", value, step)
      write_samples(samples, videos)

  def final(self, step: int, result: dict) -> None:
    """``metrics.json`` and the final metrics as TensorBoard scalars."""
    if self.is_chief:
      with open(os.path.join(self.workdir, "metrics.json"), "w") as f:
        json.dump(result, f, indent=2)
      for key, value in result.items():
        self.writer.add_scalar(f"eval/{key}", value, step)

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


def _training_batches(context: TrainContext, start: int):
  """This process's batches from step ``start`` on (batch k is a function of k alone, so the
  data reads on from a resumed step): frames ``[B/P, F, H, W, C]``, normalised actions."""
  config, members = context.config, context.data.members
  return iter(training_pipeline(
      [m.train for m in members], [m.stats for m in members],
      weights=[m.weight for m in members], batch_size=config.batch_size // jax.process_count(),
      seed=config.seed, normalization=config.data.normalization,
      action_dim=config.model.action_dim, num_workers=config.data.num_workers, start=start))


class _Run:
  """A run between its set-up and its end: the context it trains with, the state and its step,
  the batches, the checkpoints and outputs, and a signal's request to stop."""

  def __init__(self, context: TrainContext, workdir: str, is_chief: bool):
    self.context, self.config, self.workdir, self.is_chief = (context, context.config, workdir,
                                                              is_chief)
    self.saved_with = json.loads(self.config.to_json()), context.data.stats_dict()
    # RGB batches -> latents on the device (unless they were pre-encoded)
    self.encode_frames = not context.data.latents and not isinstance(context.data.codec,
                                                                     PixelCodec)
    self.encode_key = jax.random.key(self.config.seed + 1)
    self.checkpoints = Checkpointer(os.path.join(workdir, "checkpoints"),
                                    self.config.train.max_checkpoints)
    self.stop = _StopFlag()
    self.state = self.step_metrics = self.batches = self.outputs = self.bar = None
    self.trajectories: Trajectories | None = None  # held out, when the run evaluates
    self.start = self.step = 0

  def begin(self, allow: tuple[str, ...]) -> None:
    """The state restored from the newest checkpoint that reads back, or new; the batches from
    its step on, the held-out trajectories and the outputs."""
    resumed = _resume(self.checkpoints, self.context.trainer, self.config, self.workdir, allow,
                      self.is_chief)
    if resumed is None:
      self.state, self.start = self.context.trainer.init(jax.random.key(self.config.seed)), 0
      if self.config.train.init_from:
        # from host memory: every process holds the whole weights, and places its shards
        params = jax.device_put(jax.tree.map(np.asarray, initial_weights(self.config)),
                                self.context.trainer.state_shardings.params)
        # two buffers: the step donates the state, and one buffer cannot be donated twice
        self.state = self.state.replace(params=params,
                                        ema_params=jax.tree.map(jnp.copy, params))
    else:
      self.state, self.start = resumed
      print(f"resumed from step {self.start} in {self.checkpoints.directory}", flush=True)
    self.step = self.start
    self.batches = _training_batches(self.context, self.start)
    if self.config.train.eval_every > 0:
      self.trajectories = eval_trajectories(self.context.data, self.config)
    self.outputs = _RunLog(self.workdir, self.config, self.start, self.is_chief)

  def steps(self) -> None:
    """The steps up to ``train.num_steps`` or a signal, logging, saving and evaluating on the
    way."""
    from tqdm import tqdm
    every, num_steps = self.config.train, self.config.train.num_steps
    # a progress bar on a terminal; to a file (a batch job's log, nohup, CI) one plain line per
    # train.log_every steps instead of carriage-return updates on one ever-growing line
    self.plain_log = self.is_chief and plain()
    self.bar = tqdm(total=num_steps, initial=self.start,
                    disable=not self.is_chief or self.plain_log, desc="train", dynamic_ncols=True)
    tick = self.began = time.perf_counter()
    while self.step < num_steps and not self.stop.requested:
      batch = self._next_batch()
      if batch is None:
        break
      self._train_on(batch)
      if self.step % every.log_every == 0 or self.step % every.checkpoint_every == 0:
        tick = self._log(batch, tick)
      if self.step % every.checkpoint_every == 0:
        self._save()
      if (self.trajectories is not None and self.step % every.eval_every == 0
          and self.step < num_steps):
        self._evaluate_into(f"samples/step_{self.step:07d}.gif")

  def _next_batch(self) -> dict | None:
    """The next batch; None when a signal stopped the data workers too (save what there is)."""
    try:
      return next(self.batches)
    except Exception:
      if self.stop.requested:
        return None
      raise

  def _train_on(self, batch: dict) -> None:
    """One step on this process's ``batch``, made global over the mesh (encoded to latents on
    the device where the codec asks for it)."""
    trainer = self.context.trainer
    global_batch = parallel.global_batch({k: batch[k] for k in ("frames", "actions")},
                                         trainer.mesh)
    frames = global_batch["frames"]
    if self.encode_frames:  # the latents keep the batch's sharding
      key = jax.random.fold_in(self.encode_key, self.step)
      frames = jax.device_put(self.context.data.codec.encode(frames, key), frames.sharding)
    self.state, self.step_metrics = trainer.step(self.state, frames, global_batch["actions"])
    self.step += 1
    self.bar.update(1)

  def _log(self, batch: dict, tick: float) -> float:
    """The step's scalars (a NaN / inf loss stops the run, and so does a failed background
    save) and the samples per second since ``tick``, logged; returns the time now."""
    scalars = {k: float(v) for k, v in self.step_metrics.items()}
    self._check_finite(scalars["loss"])
    self.checkpoints.poll()  # a failed background save stops the run here
    now = time.perf_counter()
    scalars["samples_per_s"] = self.config.train.log_every * self.config.batch_size / (now - tick)
    self.bar.set_postfix(loss=f"{scalars['loss']:.4f}")
    if self.plain_log:
      print(progress_line(self.step, self.config.train.num_steps, self.start, scalars["loss"],
                          scalars["samples_per_s"], now - self.began), flush=True)
    self.outputs.training(self.step, scalars, batch)
    return now

  def _evaluate_into(self, samples: str, log: bool = True) -> dict:
    """:func:`evaluate` of the EMA parameters, its videos written to ``samples`` (in the
    workdir) and, with ``log``, its metrics logged at the step."""
    result, videos = evaluate(self.context, self.state.ema_params, self.trajectories,
                              jax.random.key(self.step), self.step)
    self.outputs.evaluation(self.step, result if log else {}, videos,
                            os.path.join(self.workdir, samples))
    if log:
      self.bar.write(f"step {self.step}: " + ", ".join(f"{k}={v:.4g}" for k, v in result.items()))
    return result

  def _check_finite(self, loss: float) -> None:
    if not np.isfinite(loss):
      raise NonFiniteLossError(_stop_message(self.checkpoints, self.config,
                                             f"loss is {loss} at step {self.step}"))

  def _save(self) -> None:
    """A checkpoint of the step, only of a finite state."""
    if not bool(_all_finite(self.state)):
      raise NonFiniteLossError(_stop_message(self.checkpoints, self.config, (
          f"the train state at step {self.step} holds NaN or inf values and was not saved")))
    self.checkpoints.save(self.step, self.state, *self.saved_with)

  def _save_last(self) -> None:
    """The step saved unless it is already (its loss checked first, where a step was run)."""
    self.checkpoints.wait()
    if self.step != self.checkpoints.last_saved:
      if self.step_metrics is not None:
        self._check_finite(float(self.step_metrics["loss"]))
      self._save()
    self.checkpoints.wait()

  def stopped(self) -> dict:
    """After a signal: the steps trained since the start saved -> ``{'step', 'stopped',
    'signal'}``."""
    name = signal.Signals(self.stop.signum).name
    if self.step > self.start:
      self._save_last()
    saved = (f"saved step {self.step} to {self.checkpoints.directory}"
             if self.checkpoints.last_saved == self.step else
             "no step was trained, nothing to save")
    self.bar.write(f"{name}: {saved}; stopped before step {self.config.train.num_steps} (rerun "
                   f"the same command to resume)")
    return {"step": self.step, "stopped": name, "signal": int(self.stop.signum)}

  def finish(self) -> dict:
    """The last step saved and evaluated (``rollout.gif``, ``metrics.json``) -> the metrics."""
    self._save_last()
    self.bar.close()
    result = {}
    if self.trajectories is not None:
      result = self._evaluate_into("rollout.gif", log=False)
    result["step"] = self.step
    self.outputs.final(self.step, result)
    return result

  def close(self) -> None:
    """What the run holds open, closed; a failed background save is raised unless another error
    is on its way already."""
    self.stop.restore()
    failing = sys.exc_info()[0] is not None
    try:
      self.checkpoints.close()
    except CheckpointError:
      if not failing:
        raise
    finally:
      for handle in (self.bar, self.batches, self.outputs):
        if handle is not None and hasattr(handle, "close"):
          handle.close()


def _train(config: ml_collections.ConfigDict, workdir: str,
           allow: tuple[str, ...]) -> tuple[Any, dict]:
  """The phases of a run: its context set up once (:func:`wmjax.train.context.set_up`: data,
  mesh, model, the trainer fitted to memory), the state restored or new, the steps, and the
  last save and evaluation (or a signal's stop)."""
  is_chief = jax.process_index() == 0
  context = set_up(config, log=functools.partial(print, flush=True) if is_chief
                   else lambda *_: None)
  run = _Run(context, workdir, is_chief)
  try:
    run.begin(allow)
    run.steps()
    if run.stop.requested and run.step < context.config.train.num_steps:
      return run.state, run.stopped()
    return run.state, run.finish()
  finally:
    run.close()
