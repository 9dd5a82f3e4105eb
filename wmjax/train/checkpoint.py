"""Checkpoints: train state, data-iterator state, config and action statistics saved together by
an async orbax ``CheckpointManager``; a run resumes from the latest complete checkpoint.

orbax writes each checkpoint to a temporary directory and renames it when complete, so a crash
or kill during a save leaves the previous checkpoints intact.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any, Sequence

import flax.linen as nn
import grain
import jax
import ml_collections
import orbax.checkpoint as ocp

from wmjax.codecs import Codec, make_codec
from wmjax.config import apply_overrides, model_config, sampling_config
from wmjax.parallel import local_data_mesh
from wmjax.data.stats import ActionStats
from wmjax.rollout import WorldModel


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
  manager = ocp.CheckpointManager(directory, options=ocp.CheckpointManagerOptions(create=False))
  try:
    steps = manager.all_steps()
    if not steps:
      raise FileNotFoundError(f"{directory} holds no complete checkpoint")
    if step is None:
      step = max(steps)
    elif step not in steps:
      raise ValueError(f"no checkpoint for step {step} in {directory}; steps: {sorted(steps)}")
    meta = manager.restore(step, args=ocp.args.Composite(
        config=ocp.args.JsonRestore(), action_stats=ocp.args.JsonRestore()))
    config = ml_collections.ConfigDict(meta.config)
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
    restored = manager.restore(step, args=ocp.args.Composite(
        state=ocp.args.PyTreeRestore(target, partial_restore=True,
                                     restore_args=ocp.checkpoint_utils.construct_restore_args(
                                         target))))
  finally:
    manager.close()
  weights = jax.tree.map(lambda p: p.astype(param_dtype), restored.state[key])
  return LoadedModel(config, world_model, weights,
                     ActionStats.from_dict(meta.action_stats), int(step),
                     make_codec(config.get("codec")))
