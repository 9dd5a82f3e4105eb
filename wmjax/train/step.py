"""The train step: diffusion loss, AdamW update and EMA, jitted once with explicit shardings.

``ShardedTrainer(world_model, config, mesh, frame_shape, frames)`` builds:
  ``init(rng) -> TrainState``   parameters and optimiser state laid out by the logical-axis rules
  ``step(state, frames, actions) -> (TrainState, metrics)``  batch sharded over ('data', 'fsdp'),
                                  state donated.
``frames [B, F, H, W, C]`` float32 in the model's space, ``actions [B, F-1, A]`` normalised.
"""

from __future__ import annotations

from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import ml_collections
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from wmjax import parallel
from wmjax.diffusion import diffusion_loss
from wmjax.rollout import WorldModel
from wmjax.train.checkpoint import abstract_with_shardings
from wmjax.train.state import (TrainState, create_train_state, ema_update, learning_rate_schedule,
                               make_optimizer)


def make_train_step(world_model: WorldModel, config: ml_collections.ConfigDict,
                    tx: optax.GradientTransformation):
  """The pure train step ``(state, frames, actions) -> (state, metrics)``."""
  net, process, diffusion = world_model.network, world_model.process, config.diffusion
  schedule = learning_rate_schedule(config.optim)

  def step(state: TrainState, frames: jax.Array, actions: jax.Array):
    key = jax.random.fold_in(jax.random.wrap_key_data(state.rng), state.step)
    dropout_key, diffusion_key = jax.random.split(key)

    def loss_fn(params):
      def denoise(x, levels):
        return net.apply({"params": params}, x, process.model_time(levels), actions, train=True,
                         rngs={"dropout": dropout_key})
      return diffusion_loss(denoise, process, frames, diffusion_key, diffusion.regime,
                            diffusion.num_context)

    (loss, _), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params["params"])
    updates, opt_state = tx.update({"params": grads}, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    new_state = state.replace(step=state.step + 1, params=params, opt_state=opt_state,
                              ema_params=ema_update(state.ema_params, params,
                                                    config.optim.ema_decay, state.step))
    metrics = {"loss": loss, "grad_norm": optax.tree.norm(grads),
               "learning_rate": schedule(state.step)}
    return new_state, metrics

  return step


def check_batch_shapes(world_model: WorldModel, frames_shape, actions_shape, mesh: Mesh) -> None:
  """ValueError before compilation for a batch the model or the mesh cannot take."""
  net = world_model.network
  if len(frames_shape) != 5 or len(actions_shape) != 3:
    raise ValueError(f"batch must hold frames [B, F, H, W, C] and actions [B, F-1, A], got "
                     f"{tuple(frames_shape)} and {tuple(actions_shape)}")
  if actions_shape[-1] != net.action_dim:
    raise ValueError(f"the data has {actions_shape[-1]}-dim actions but the model expects "
                     f"{net.action_dim} (model.action_dim)")
  net.check_inputs(jax.ShapeDtypeStruct(frames_shape, jnp.float32),
                   jax.ShapeDtypeStruct(frames_shape[:2], jnp.float32),
                   jax.ShapeDtypeStruct(actions_shape, jnp.float32))
  shards = mesh.shape["data"] * mesh.shape["fsdp"]
  if frames_shape[0] % shards:
    raise ValueError(f"global batch {frames_shape[0]} is not divisible by the data-parallel size "
                     f"{shards} (mesh data x fsdp = {mesh.shape['data']} x {mesh.shape['fsdp']})")


class ShardedTrainer:
  """Jitted, sharded ``init`` and ``step`` for one world model, config and mesh."""

  def __init__(self, world_model: WorldModel, config: ml_collections.ConfigDict, mesh: Mesh,
               frame_shape: tuple[int, int, int], frames: int):
    self.world_model, self.mesh = world_model, mesh
    self.tx = make_optimizer(config.optim)

    def init(rng):
      param_rng, state_rng = jax.random.split(rng)
      return create_train_state(world_model.init(param_rng, frame_shape, frames), self.tx,
                                state_rng)

    abstract = jax.eval_shape(init, jax.random.key(0))
    self.state_shardings = parallel.logical_shardings(abstract, mesh)
    self.abstract_state = abstract_with_shardings(nn.unbox(abstract), self.state_shardings)
    self.batch_sharding = parallel.batch_sharding(mesh)
    replicated = NamedSharding(mesh, PartitionSpec())
    self._init = jax.jit(lambda rng: nn.unbox(init(rng)), out_shardings=self.state_shardings)
    self._step = jax.jit(make_train_step(world_model, config, self.tx),
                         in_shardings=(self.state_shardings, self.batch_sharding,
                                       self.batch_sharding),
                         out_shardings=(self.state_shardings, replicated), donate_argnums=0)
    self._compiled: dict[tuple, jax.stages.Compiled] = {}

  # Both run with the mesh in context, for kernels that are split over it by hand (splash).

  def init(self, rng: jax.Array) -> TrainState:
    with jax.set_mesh(self.mesh):
      return self._init(rng)

  def step(self, state: TrainState, frames: Any, actions: Any):
    check_batch_shapes(self.world_model, frames.shape, actions.shape, self.mesh)
    step = self._compiled.get(_batch_key(frames, actions), self._step)
    with jax.set_mesh(self.mesh):
      return step(state, frames, actions)

  def compile(self, state: Any, frames: Any, actions: Any) -> jax.stages.Compiled:
    """The step compiled ahead of time for this batch (arrays or ``jax.ShapeDtypeStruct``s);
    later :meth:`step` calls with the same batch shapes run it instead of compiling again.
    ``.memory_analysis()`` gives its per-device argument, output and temporary bytes."""
    check_batch_shapes(self.world_model, frames.shape, actions.shape, self.mesh)
    key = _batch_key(frames, actions)
    if key not in self._compiled:
      with jax.set_mesh(self.mesh):
        self._compiled[key] = self._step.lower(state, frames, actions).compile()
    return self._compiled[key]


def _batch_key(frames: Any, actions: Any) -> tuple:
  return (tuple(frames.shape), str(frames.dtype), tuple(actions.shape), str(actions.dtype))
