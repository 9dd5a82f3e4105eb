"""Checkpoints: train state, data-iterator state, config and action statistics saved together by
an async orbax ``CheckpointManager``; a run resumes from the latest complete checkpoint.

orbax writes each checkpoint to a temporary directory and renames it when complete, so a crash
or kill during a save leaves the previous checkpoints intact.
"""

from __future__ import annotations

import os
from typing import Any

import grain
import jax
import orbax.checkpoint as ocp


class Checkpointer:
  def __init__(self, directory: str, max_to_keep: int = 3):
    self.directory = os.path.abspath(directory)
    options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True,
                                           enable_async_checkpointing=True)
    self.manager = ocp.CheckpointManager(self.directory, options=options)

  def latest_step(self) -> int | None:
    return self.manager.latest_step()

  def save(self, step: int, state: Any, data_iterator: Any, config: dict,
           action_stats: dict) -> None:
    """Start an async save of everything a resumed run needs."""
    self.manager.save(step, args=ocp.args.Composite(
        state=ocp.args.StandardSave(state),
        data=grain.checkpoint.CheckpointSave(data_iterator),
        config=ocp.args.JsonSave(config),
        action_stats=ocp.args.JsonSave(action_stats)), force=True)

  def restore(self, step: int, abstract_state: Any, data_iterator: Any) -> tuple[Any, dict, dict]:
    """State laid out like ``abstract_state`` (ShapeDtypeStructs with shardings); the iterator is
    restored in place. Returns (state, config, action_stats)."""
    restored = self.manager.restore(step, args=ocp.args.Composite(
        state=ocp.args.StandardRestore(abstract_state),
        data=grain.checkpoint.CheckpointRestore(data_iterator),
        config=ocp.args.JsonRestore(),
        action_stats=ocp.args.JsonRestore()))
    return restored.state, restored.config, restored.action_stats

  def wait(self) -> None:
    self.manager.wait_until_finished()

  def close(self) -> None:
    self.manager.close()


def abstract_with_shardings(abstract: Any, shardings: Any) -> Any:
  """ShapeDtypeStructs carrying the shardings to restore into."""
  return jax.tree.map(lambda a, s: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s), abstract,
                      shardings)
