"""Checkpoints: train state, config and action statistics saved together by an async orbax
``CheckpointManager``; a run resumes from the newest checkpoint that reads back.

orbax writes each checkpoint to a temporary directory and renames it when complete, so a crash
or kill during a save leaves the previous checkpoints intact; temporary directories left by a
kill are removed when the next run opens the directory. A background save that fails is
reported by :meth:`Checkpointer.poll` once it has finished (the loop calls it at every logged step),
as a :class:`CheckpointError` with a one-line message. The data iterator needs no state of its
own: batch ``k`` of :func:`wmjax.data.pipeline.training_pipeline` is a function of ``k``, so a run
resumed at step ``k`` reads on from batch ``k``.
"""

from __future__ import annotations

import glob
import os
import shutil
import sys
import time
from typing import Any, Callable

import jax
import numpy as np
import orbax.checkpoint as ocp

from wmjax.errors import CheckpointError, describe_error, ignore_closed_loop_callbacks

TMP_MARKER = ".orbax-checkpoint-tmp"

# orbax writes a replicated array cooperatively, each replica a slice of it, and takes every slice
# with its own small XLA program (compiled once per device and shape): for the many small arrays of
# a state (biases, norms, optimizer counts) that is all overhead, 144 compiles on the first save of
# a tiny model on 8 devices. Arrays whose slice would be smaller than this are written whole from
# one replica; the large ones stay cooperative.
MIN_SLICE_BYTES_FOR_REPLICA_PARALLEL = 1 << 20


def state_handler() -> ocp.PyTreeCheckpointHandler:
  """The orbax handler of the train state: the standard types, replica-parallel writes only for
  slices of at least :data:`MIN_SLICE_BYTES_FOR_REPLICA_PARALLEL` bytes."""
  registry = ocp.type_handlers.create_type_handler_registry(
      (int, ocp.type_handlers.ScalarHandler()), (float, ocp.type_handlers.ScalarHandler()),
      (np.number, ocp.type_handlers.ScalarHandler()),
      (np.ndarray, ocp.type_handlers.NumpyHandler()), (str, ocp.type_handlers.StringHandler()),
      (jax.Array, ocp.type_handlers.ArrayHandler(
          min_slice_bytes_for_replica_parallel=MIN_SLICE_BYTES_FOR_REPLICA_PARALLEL)))
  return ocp.PyTreeCheckpointHandler(type_handler_registry=registry)


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
        "state": state_handler(), "config": ocp.JsonCheckpointHandler(),
        "action_stats": ocp.JsonCheckpointHandler()})
    ignore_closed_loop_callbacks()
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
          state=ocp.args.PyTreeSave(state),
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
      self._remove_partial(step)
    kept = (f"checkpoint {self.last_saved} is intact; fix the cause and rerun to resume from it"
            if self.last_saved is not None else "no checkpoint was saved before it")
    raise CheckpointError(f"saving checkpoint {step} to {self.directory} failed: "
                          f"{describe_error(error)}. Training stopped; {kept}.") from error

  def _remove_partial(self, step: int, quiet_s: float = 1.0, timeout_s: float = 30.0):
    """Remove the partial write of checkpoint ``step`` until it stays gone for ``quiet_s``.

    Orbax raises at the first failed item while the writers of the other items may still be
    running; removed under them, they would recreate files in the directory.
    """
    pattern = os.path.join(self.directory, f"{step}{TMP_MARKER}*")
    deadline, quiet_since = time.monotonic() + timeout_s, None
    while time.monotonic() < deadline:
      partials = glob.glob(pattern)
      for partial in partials:
        shutil.rmtree(partial, ignore_errors=True)
      now = time.monotonic()
      quiet_since = None if partials else (quiet_since or now)
      if quiet_since is not None and now - quiet_since >= quiet_s:
        return
      time.sleep(0.1)

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
        state=ocp.args.PyTreeRestore(abstract_state, restore_args=(
            ocp.checkpoint_utils.construct_restore_args(abstract_state))))).state

  def _read(self, step: int, item: str, args: ocp.args.Composite):
    try:
      return self.manager.restore(step, args=args)
    except Exception as e:
      raise self._unreadable(step, item, e) from e

  def _unreadable(self, step: int, item: str, error: BaseException) -> CheckpointError:
    return CheckpointError(f"checkpoint {step} cannot be read: "
                           f"{os.path.join(self.directory, str(step), item)}: "
                           f"{describe_error(error)}")

  def restore_newest(self, check: Callable[[int, dict, dict], tuple[Any, Any]],
                     damaged_dir: str) -> tuple[Any, int, Any] | None:
    """``(state, step, check's answer)`` of the newest checkpoint that reads back, or None when
    there is none. ``check(step, saved config, stored shapes)`` runs before the state is read:
    it returns ``(answer, abstract state to read it into)`` or raises to refuse it (a refusal
    stops the search). A damaged newer checkpoint is moved to ``damaged_dir`` (kept, never
    deleted) with a warning; with several processes it stops the run instead, naming the intact
    one."""
    damaged = []
    for step in reversed(self.all_steps()):
      try:
        answer, abstract_state = check(step, self.read_config(step), self.stored_shapes(step))
        state = self.restore(step, abstract_state)
      except CheckpointError as e:
        damaged.append((step, e))
        print(f"WARNING: {e}", file=sys.stderr, flush=True)
        continue
      if damaged and jax.process_count() > 1:
        raise CheckpointError(f"{damaged[0][1]}. Checkpoint {step} is intact: move "
                              f"{self.directory}/{damaged[0][0]} (and any newer) aside and "
                              f"rerun to resume from it.")
      for bad, _ in damaged:
        where = self.set_aside(bad, damaged_dir)
        print(f"WARNING: checkpoint {bad} is damaged and was moved to {where}; resuming from "
              f"checkpoint {step}, the newest intact one.", file=sys.stderr, flush=True)
      return state, step, answer
    if damaged:
      raise CheckpointError(
          "no checkpoint in " + self.directory + " can be read: " + "; ".join(
              str(e) for _, e in damaged) + ". Move the directory aside to start afresh.")
    return None

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
