"""A training run set up once: the mesh, the world model, the trainer and the data, built in one
place (as maxtext's ``setup_train_loop`` builds the context that its ahead-of-time compile
reuses).

:func:`build_context` makes the mesh of ``config.mesh`` over a target's devices, the world model
and its sharded trainer; :func:`compile_step` compiles that trainer's step for the target and
reports its memory (:mod:`wmjax.train.aot` does so for ``wmjax compile``, without the hardware).
:func:`set_up` is a run's: the data, the context on this job's devices, and the step compiled and
fitted to the device's memory (:func:`fit_to_memory`): :mod:`wmjax.train.fit` chooses remat and
gradient accumulation, applied to the same mesh and model (:meth:`TrainContext.with_setting`).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import ml_collections
from jax.sharding import Mesh

from wmjax import parallel
from wmjax.model import WorldModel
from wmjax.nn import attention, forward_flops
from wmjax.train import fit
from wmjax.train.data import TrainData, build_data
from wmjax.train.self_forcing import model_frames
from wmjax.train.step import ShardedTrainer


@dataclasses.dataclass(frozen=True)
class TrainContext:
  """What a run trains with: ``world_model`` on ``mesh``, a mesh over the devices of ``target``;
  its :attr:`trainer` is built when first asked for."""

  config: ml_collections.ConfigDict  # as trained: model.remat and optim.grad_accum as fitted
  target: fit.Target
  mesh: Mesh
  world_model: WorldModel
  data: TrainData | None = None  # None where the step is only compiled

  @functools.cached_property
  def trainer(self) -> ShardedTrainer:
    """The sharded trainer of ``world_model`` on windows of ``data.frames`` frames (the model's
    ``num_frames`` for a config without data), its attention built for the target's platform."""
    config = self.config
    frames = config.data.frames if "data" in config else self.world_model.network.num_frames
    return ShardedTrainer(self.world_model, config, self.mesh, tuple(config.frame_shape), frames,
                          self.target.platform)

  def with_setting(self, remat: str, grad_accum: int) -> TrainContext:
    """The same mesh, model and data with ``model.remat`` and ``optim.grad_accum`` changed (and
    a trainer of its own)."""
    world_model = dataclasses.replace(self.world_model,
                                      network=self.world_model.network.clone(remat=remat))
    return dataclasses.replace(self, config=with_setting(self.config, remat, grad_accum),
                               world_model=world_model)

  @property
  def data_parallel(self) -> int:
    """The devices a global batch is split over (the mesh's ``data`` x ``fsdp``)."""
    return self.mesh.shape["data"] * self.mesh.shape["fsdp"]


def build_context(config: ml_collections.ConfigDict, target: fit.Target,
                  data: TrainData | None = None) -> TrainContext:
  """The world model of ``config`` and the mesh of ``config.mesh`` over the devices of
  ``target`` (its trainer, which checks the mesh against the model, follows on first use)."""
  world_model = WorldModel.from_config(config)
  return TrainContext(config, target, parallel.make_mesh(tuple(config.mesh), list(target.devices)),
                      world_model, data)


def compile_step(context: TrainContext, batch: int | None = None,
                 budget_bytes: int | None = None) -> tuple[jax.stages.Compiled | None, dict]:
  """The trainer's step compiled for the context's target at global ``batch`` (default
  ``config.batch_size``, checked against the mesh and this job's processes first) -> (compiled
  step, report): per-device memory (GiB) and whether it fits
  ``budget_bytes`` (:func:`wmjax.train.fit.memory_report`), what it executes and its predicted
  time (:func:`wmjax.train.fit.cost_report`), the mesh, the attention path, XLA's and the
  analytic FLOPs and the compile time. Later steps of the trainer reuse the compiled
  step. A step the compiler refuses for want of memory comes back as None with
  :func:`wmjax.train.fit.refused_report`."""
  trainer, net, target = context.trainer, context.world_model.network, context.target
  batch = batch or context.config.batch_size
  start = time.perf_counter()
  frames = jax.ShapeDtypeStruct((batch, trainer.frames) + trainer.frame_shape, jnp.float32,
                                sharding=trainer.batch_sharding)
  actions = jax.ShapeDtypeStruct((batch, trainer.frames - 1, net.action_dim), jnp.float32,
                                 sharding=trainer.batch_sharding)
  try:
    compiled = trainer.compile(trainer.abstract_state, frames, actions)
    report = {**fit.memory_report(compiled, target, budget_bytes),
              **fit.cost_report(compiled, target)}
  except jax.errors.JaxRuntimeError as e:
    compiled, report = None, fit.refused_report(e, target, budget_bytes)
    if report is None:
      raise
  height, width = trainer.frame_shape[:2]
  return compiled, {
      "what": "train", "target": target.spec, "platform": target.platform,
      "devices": len(target.devices), "mesh": dict(context.mesh.shape), "batch": batch,
      "frames": trainer.frames, "remat": net.remat, "grad_accum": trainer.micro_batches,
      "dtype": str(net.dtype),
      "attention": attention.resolve_backend(net.attention_impl, net.dtype, target.platform),
      **report,
      "analytic_flops": 3 * forward_flops(net, batch, model_frames(context.config), height,
                                          width),
      "compile_s": time.perf_counter() - start,
  }


def _measure(context: TrainContext, batch: int | None) -> fit.Measure:
  """The fit's measure of ``context``: a setting and a budget -> (its context, its compiled
  step's report)."""
  def measure(remat: str, grad_accum: int, budget_bytes: int | None) -> tuple[TrainContext, dict]:
    own = (context.config.model.remat, context.config.optim.grad_accum) == (remat, grad_accum)
    candidate = context if own else context.with_setting(remat, grad_accum)
    return candidate, compile_step(candidate, batch, budget_bytes)[1]
  return measure


def fit_context(context: TrainContext, budget_bytes: int | None = None, batch: int | None = None,
                first: tuple[TrainContext, dict] | None = None, log=print
                ) -> tuple[TrainContext, dict]:
  """:func:`wmjax.train.fit.fit_step` over the settings of ``context``: the context of the
  setting predicted fastest of those whose compiled step fits ``budget_bytes``, and its report."""
  return fit.fit_step(context.config, context.target, _measure(context, batch),
                      context.data_parallel, budget_bytes, batch, first, log)


def with_setting(config: ml_collections.ConfigDict, remat: str, grad_accum: int
                 ) -> ml_collections.ConfigDict:
  """A copy of ``config`` with ``model.remat`` and ``optim.grad_accum`` set."""
  updated = copy.deepcopy(config)
  with updated.unlocked():
    updated.model.remat = remat
    updated.optim.grad_accum = grad_accum
  return updated


def fit_to_memory(context: TrainContext, log=print) -> tuple[TrainContext, dict]:
  """Before the first step: the step compiled on the context's devices against the training
  budget and, where it does not fit and ``train.auto_fit`` allows, the setting predicted fastest
  of those that do (:func:`wmjax.train.fit.fit_for_training`) -> (context as trained, its
  report)."""
  return fit.fit_for_training(context.config, context.target, _measure(context, None),
                              context.data_parallel, log)


def set_up(config: ml_collections.ConfigDict, log=print) -> TrainContext:
  """A run's context: its data (checked against the model), the mesh over this job's devices,
  the world model and the trainer with its step compiled and fitted to the device's memory (the
  compiled step's memory is logged; ``wmjax info`` gives the analytic estimate)."""
  data = build_data(config, evaluation=config.train.eval_every > 0)
  return fit_to_memory(build_context(config, fit.parse_target("local"), data), log)[0]
