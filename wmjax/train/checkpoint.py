"""Checkpoints: train state, config and action statistics saved together by an async orbax
``CheckpointManager``; a run resumes from the newest checkpoint that reads back.

orbax writes each checkpoint to a temporary directory and renames it when complete, so a crash
or kill during a save leaves the previous checkpoints intact; temporary directories left by a
kill are removed when the next run opens the directory. A background save that fails is
reported by :meth:`Checkpointer.poll` as soon as it has finished (the loop calls it every step),
as a :class:`CheckpointError` with a one-line message. The data iterator needs no state of its
own: batch ``k`` of :func:`wmjax.data.pipeline.training_pipeline` is a function of ``k``, so a run
resumed at step ``k`` reads on from batch ``k``.
"""

from __future__ import annotations

import dataclasses
import errno
import glob
import os
import shutil
from typing import Any, Sequence

import flax.linen as nn
import jax
import ml_collections
import orbax.checkpoint as ocp

from wmjax.codecs import Codec, make_codec
from wmjax.config import apply_overrides, model_config, sampling_config
from wmjax.parallel import local_data_mesh
from wmjax.data.stats import ActionStats
from wmjax.rollout import WorldModel
from wmjax.train.errors import RunError

TMP_MARKER = ".orbax-checkpoint-tmp"


class CheckpointError(RunError):
  """A checkpoint cannot be written or read back."""


def describe_error(error: BaseException, limit: int = 500) -> str:
  """``Type: first line of the message`` of an exception, or of the ``OSError`` behind it (a full
  disk is reported as such however deep orbax or tensorstore wrapped it)."""
  seen, cause = set(), error
  while cause is not None and id(cause) not in seen:
    seen.add(id(cause))
    if isinstance(cause, OSError) and cause.errno is not None:
      error = cause
      break
    cause = cause.__cause__ or cause.__context__
  if isinstance(error, OSError) and error.errno is not None:
    text = f"{os.strerror(error.errno)} ({errno.errorcode.get(error.errno, error.errno)})"
    if error.filename:
      text += f": {error.filename}"
  else:
    lines = str(error).strip().splitlines()
    first = lines[0].split(" [tensorstore_spec=")[0] if lines else ""
    text = f"{type(error).__name__}: {first}".rstrip(": ")
  if "RESOURCE_EXHAUSTED" in text or "No space left" in text:
    text = "the disk is full (" + text + ")"
  return text if len(text) <= limit else text[:limit - 3] + "..."


def _ignore_closed_loop_callbacks() -> None:
  """After a failed read, tensorstore still completes the other reads of the batch and hands
  their results to orbax's event loop, which the failure has closed: every one of them would
  print a ``RuntimeError: Event loop is closed`` traceback (hundreds, burying the real error,
  which is reported on its own). Drop exactly those; other unraisable errors go through."""
  import sys
  previous = sys.unraisablehook
  if getattr(previous, "_wmjax", False):
    return

  def hook(unraisable):
    value = unraisable.exc_value
    if isinstance(value, RuntimeError) and str(value) == "Event loop is closed":
      return
    previous(unraisable)

  hook._wmjax = True
  sys.unraisablehook = hook


def _path_names(path) -> tuple[str, ...]:
  return tuple(str(getattr(k, "key", getattr(k, "name", getattr(k, "idx", k)))) for k in path)


def shapes_by_path(tree: Any) -> dict[str, tuple[int, ...]]:
  """``'params/blocks/kernel' -> shape`` for every array leaf of a state, an abstract state or
  orbax's metadata of one (attribute, key and index names alike)."""
  leaves = jax.tree_util.tree_leaves_with_path(tree, is_leaf=lambda x: hasattr(x, "shape"))
  return {"/".join(_path_names(path)): tuple(leaf.shape) for path, leaf in leaves
          if hasattr(leaf, "shape")}


class Checkpointer:
  """The checkpoints of one training run: async saves, their errors surfaced at once, and
  restores that say which checkpoint and which part of it could not be read."""

  def __init__(self, directory: str, max_to_keep: int = 3):
    self.directory = os.path.abspath(directory)
    options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True,
                                           enable_async_checkpointing=True,
                                           cleanup_tmp_directories=True)
    self.manager = ocp.CheckpointManager(self.directory, options=options, item_handlers={
        "state": ocp.StandardCheckpointHandler(), "config": ocp.JsonCheckpointHandler(),
        "action_stats": ocp.JsonCheckpointHandler()})
    _ignore_closed_loop_callbacks()
    self._pending: int | None = None  # step of the save in flight
    self.last_saved: int | None = self.latest_step()  # newest complete checkpoint

  def latest_step(self) -> int | None:
    return self.manager.latest_step()

  def all_steps(self) -> list[int]:
    return sorted(self.manager.all_steps())

  def save(self, step: int, state: Any, config: dict, action_stats: dict) -> None:
    """Start an async save of everything a resumed run needs (after checking that the previous
    save succeeded)."""
    self.wait()
    try:
      self.manager.save(step, args=ocp.args.Composite(
          state=ocp.args.StandardSave(state),
          config=ocp.args.JsonSave(config),
          action_stats=ocp.args.JsonSave(action_stats)), force=True)
    except Exception as e:  # the synchronous part (directories, metadata) failed
      self._failed(step, e)
    self._pending = step

  def poll(self) -> None:
    """Raise :class:`CheckpointError` if the save in flight has failed; never blocks."""
    if self._pending is not None and not self.manager.is_saving_in_progress():
      self.wait()

  def wait(self) -> None:
    """Block until the save in flight is complete; :class:`CheckpointError` if it failed."""
    if self._pending is None:
      return
    step, self._pending = self._pending, None
    try:
      self.manager.wait_until_finished()
    except Exception as e:
      self._failed(step, e)
    self.last_saved = step

  def _failed(self, step: int, error: BaseException):
    self._pending = None
    if jax.process_index() == 0:  # the partial write, e.g. what filled the disk
      for partial in glob.glob(os.path.join(self.directory, f"{step}{TMP_MARKER}*")):
        shutil.rmtree(partial, ignore_errors=True)
    kept = (f"checkpoint {self.last_saved} is intact; fix the cause and rerun to resume from it"
            if self.last_saved is not None else "no checkpoint was saved before it")
    raise CheckpointError(f"saving checkpoint {step} to {self.directory} failed: "
                          f"{describe_error(error)}. Training stopped; {kept}.") from error

  def read_config(self, step: int) -> dict:
    """The config saved with checkpoint ``step``; :class:`CheckpointError` naming the item if it
    cannot be read."""
    return self._read(step, "config", ocp.args.Composite(config=ocp.args.JsonRestore())).config

  def stored_shapes(self, step: int) -> dict[str, tuple[int, ...]]:
    """Shapes of the saved state's arrays, from the checkpoint's metadata (no array is read)."""
    try:
      metadata = self.manager.item_metadata(step).state
    except Exception as e:
      raise self._unreadable(step, "state", e) from e
    if metadata is None:
      raise self._unreadable(step, "state", FileNotFoundError("no state metadata"))
    return shapes_by_path(getattr(metadata, "tree", metadata))

  def restore(self, step: int, abstract_state: Any) -> Any:
    """The state laid out like ``abstract_state`` (ShapeDtypeStructs with shardings)."""
    return self._read(step, "state", ocp.args.Composite(
        state=ocp.args.StandardRestore(abstract_state))).state

  def _read(self, step: int, item: str, args: ocp.args.Composite):
    try:
      return self.manager.restore(step, args=args)
    except Exception as e:
      raise self._unreadable(step, item, e) from e

  def _unreadable(self, step: int, item: str, error: BaseException) -> CheckpointError:
    return CheckpointError(f"checkpoint {step} cannot be read: "
                           f"{os.path.join(self.directory, str(step), item)}: "
                           f"{describe_error(error)}")

  def set_aside(self, step: int, destination: str) -> str:
    """Move checkpoint ``step`` out of the way (kept, never deleted) to ``destination/step``."""
    target = os.path.join(destination, str(step))
    suffix = 1
    while os.path.exists(target):
      target, suffix = os.path.join(destination, f"{step}.{suffix}"), suffix + 1
    os.makedirs(destination, exist_ok=True)
    shutil.move(os.path.join(self.directory, str(step)), target)
    self.manager.reload()
    self.last_saved = self.latest_step()
    return target

  def close(self) -> None:
    """Wait for the save in flight and release orbax's threads; a failure of that save was
    raised by :meth:`wait` already or is raised here."""
    try:
      self.wait()
    finally:
      try:
        self.manager.close()
      except Exception:  # the failed save, reported above
        pass


def abstract_with_shardings(abstract: Any, shardings: Any) -> Any:
  """ShapeDtypeStructs carrying the shardings to restore into."""
  return jax.tree.map(lambda a, s: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s), abstract,
                      shardings)


# ----------------------------------------------------------------------------- inference


@dataclasses.dataclass(frozen=True)
class LoadedModel:
  """A trained world model ready for rollouts, read from a training workdir."""

  config: ml_collections.ConfigDict
  world_model: WorldModel
  params: Any  # EMA or raw parameters, replicated over the local devices
  action_stats: ActionStats
  step: int
  codec: Codec  # RGB frames <-> the model's space (config.codec)

  @property
  def frame_shape(self) -> tuple[int, int, int]:
    """The model's frames (latents for a VAE codec)."""
    return tuple(self.config.frame_shape)

  @property
  def image_shape(self) -> tuple[int, int, int]:
    """The RGB frames the codec takes."""
    return self.codec.image_shape(self.frame_shape)


def load_model(workdir: str, *, step: int | None = None, params: str = "ema",
               overrides: Sequence[str] = (), param_dtype: str = "float32") -> LoadedModel:
  """The parameters (``params='ema'`` or ``'raw'``), config and action statistics of a training
  checkpoint in ``workdir`` (the latest, or ``step``); nothing else of the train state is read.
  ``overrides`` (``dotted.key=value``) change inference settings such as ``sampling.num_steps``
  or ``model.dtype``; ``param_dtype='bfloat16'`` halves the parameters' memory for inference."""
  if params not in ("ema", "raw"):
    raise ValueError(f"params must be 'ema' or 'raw', got {params!r}")
  directory = os.path.join(os.path.abspath(os.path.expanduser(workdir)), "checkpoints")
  if not os.path.isdir(directory):
    raise FileNotFoundError(f"{workdir} holds no checkpoints/ directory; train a model there "
                            f"first (wmjax train --workdir {workdir})")
  _ignore_closed_loop_callbacks()
  manager = ocp.CheckpointManager(directory, options=ocp.CheckpointManagerOptions(create=False))
  try:
    steps = sorted(manager.all_steps())
    if not steps:
      raise FileNotFoundError(f"{directory} holds no complete checkpoint")
    if step is None:
      step = steps[-1]
    elif step not in steps:
      raise ValueError(f"no checkpoint for step {step} in {directory}; steps: {steps}")

    def read(item, args):
      try:
        return manager.restore(step, args=ocp.args.Composite(**args))
      except Exception as e:
        others = [s for s in steps if s != step]
        hint = (f"; the other checkpoints are steps {others}: pass --step {others[-1]} (or "
                f"step={others[-1]}) to use one" if others else "")
        raise CheckpointError(f"checkpoint {step} cannot be read: "
                              f"{os.path.join(directory, str(step), item)}: "
                              f"{describe_error(e)}{hint}") from e

    config = ml_collections.ConfigDict(read("config", dict(config=ocp.args.JsonRestore())).config)
    stats = read("action_stats", dict(action_stats=ocp.args.JsonRestore())).action_stats
    # A checkpoint written before a model or sampling field existed gets its default, which an
    # override may then change (e.g. sampling.kv_cache).
    config.model = model_config(**config.model.to_dict())
    config.sampling = sampling_config(**config.sampling.to_dict())
    config = apply_overrides(config, overrides)
    world_model = WorldModel.from_config(config)
    frame_shape = tuple(config.frame_shape)
    abstract = nn.unbox(jax.eval_shape(
        lambda: world_model.init(jax.random.key(0), frame_shape, config.data.frames)))
    replicated = jax.sharding.NamedSharding(local_data_mesh(), jax.sharding.PartitionSpec())
    key = "ema_params" if params == "ema" else "params"
    target = {key: abstract_with_shardings(abstract, jax.tree.map(lambda _: replicated, abstract))}
    restored = read("state", dict(state=ocp.args.PyTreeRestore(
        target, partial_restore=True,
        restore_args=ocp.checkpoint_utils.construct_restore_args(target))))
  finally:
    manager.close()
  weights = jax.tree.map(lambda p: p.astype(param_dtype), restored.state[key])
  return LoadedModel(config, world_model, weights,
                     ActionStats.from_dict(stats), int(step),
                     make_codec(config.get("codec")))
