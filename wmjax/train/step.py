"""The train step: diffusion loss, AdamW update and EMA, jitted once with explicit shardings; its
state (params, EMA params, optimiser state, step, RNG) and optimiser.

``ShardedTrainer(world_model, config, mesh, frame_shape, frames, platform)`` builds:
  ``init(rng) -> TrainState``   parameters and optimiser state laid out by the logical-axis rules
  ``step(state, frames, actions) -> (TrainState, metrics)``  batch sharded over ('data', 'fsdp'),
                                  state donated.
``frames [B, F, H, W, C]`` float32 in the model's space, ``actions [B, F-1, A]`` normalised.
"""

from __future__ import annotations

from typing import Any

import flax
import flax.linen as nn
import jax
import jax.numpy as jnp
import ml_collections
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from wmjax import parallel
from wmjax.config import ConfigError
from wmjax.diffusion import LevelSampling, masked_loss_sum, training_noise
from wmjax.model import WorldModel
from wmjax.nn import attention
from wmjax.parallel import abstract_with_shardings
from wmjax.train.self_forcing import self_forced_windows


SCHEDULES = ("constant", "warmup", "cosine")


@flax.struct.dataclass
class TrainState:
  step: jax.Array  # int32 scalar: optimiser updates done
  params: Any
  ema_params: Any
  opt_state: optax.OptState
  rng: jax.Array  # uint32 PRNG key data; step keys are fold_in(wrap_key_data(rng), step)


def learning_rate_schedule(optim: ml_collections.ConfigDict) -> optax.Schedule:
  lr, warmup = optim.learning_rate, optim.warmup_steps
  if optim.schedule == "constant":
    return optax.constant_schedule(lr)
  if optim.schedule == "warmup":
    return optax.linear_schedule(0.0, lr, max(warmup, 1))
  if optim.schedule == "cosine":
    if warmup >= optim.total_steps:
      raise ValueError(f"the cosine schedule needs optim.warmup_steps < optim.total_steps, got "
                       f"{warmup} and {optim.total_steps}")
    return optax.warmup_cosine_decay_schedule(0.0, lr, max(warmup, 1), max(optim.total_steps, 2))
  raise ValueError(f"optim.schedule must be one of {SCHEDULES}, got {optim.schedule!r}")


def make_optimizer(optim: ml_collections.ConfigDict) -> optax.GradientTransformation:
  """AdamW with global-norm clipping (gradient accumulation happens inside the train step)."""
  tx = optax.adamw(learning_rate_schedule(optim), b1=optim.b1, b2=optim.b2,
                   weight_decay=optim.weight_decay)
  if optim.grad_clip > 0:
    tx = optax.chain(optax.clip_by_global_norm(optim.grad_clip), tx)
  return tx


def create_train_state(params: Any, tx: optax.GradientTransformation, rng: jax.Array
                       ) -> TrainState:
  """A fresh state; ``params`` may carry logical-axis boxes (kept, for sharding rules)."""
  return TrainState(step=jnp.zeros((), jnp.int32), params=params, ema_params=params,
                    opt_state=tx.init(params), rng=jax.random.key_data(rng))


def ema_update(ema: Any, params: Any, decay: float, step: jax.Array) -> Any:
  """EMA with warm-up: the decay used at update ``step`` is ``min(decay, (1+step)/(10+step))``,
  so that short runs are not dominated by the initial parameters."""
  step = jnp.asarray(step, jnp.float32)
  d = jnp.minimum(decay, (1.0 + step) / (10.0 + step))
  return jax.tree.map(lambda e, p: d * e + (1.0 - d) * p, ema, params)


def make_train_step(world_model: WorldModel, config: ml_collections.ConfigDict,
                    tx: optax.GradientTransformation):
  """The pure train step ``(state, frames, actions) -> (state, metrics)``.

  With ``diffusion.self_forcing`` the batch holds windows one frame longer than the model's,
  and some of them get a context frame the model samples itself
  (:mod:`wmjax.train.self_forcing`) before anything else. The randomness of the whole batch
  (noise levels, noise, action dropout) is drawn first; with
  ``optim.grad_accum = k > 1`` the batch is then cut into k equal micro-batches whose gradients
  are summed in a ``lax.scan`` before one update, so that only one micro-batch's activations are
  alive at a time. The loss and update equal the whole batch's up to float rounding.
  """
  net, process, diffusion = world_model.network, world_model.process, config.diffusion
  schedule = learning_rate_schedule(config.optim)
  micro = config.optim.grad_accum
  level_sampling = LevelSampling.from_config(diffusion)

  def step(state: TrainState, frames: jax.Array, actions: jax.Array):
    key = jax.random.fold_in(jax.random.wrap_key_data(state.rng), state.step)
    noise_key, dropout_key = jax.random.split(key)
    if diffusion.self_forcing:
      frames, actions = jax.lax.cond(
          state.step >= diffusion.self_forcing_start,
          lambda: self_forced_windows(world_model, state.ema_params, frames, actions,
                                      diffusion.self_forcing, diffusion.num_context,
                                      jax.random.fold_in(key, 1)),
          lambda: (frames[:, 1:], actions[:, 1:]))
    b = frames.shape[0]
    levels, mask, noise = training_noise(process, noise_key, frames.shape, diffusion.regime,
                                         diffusion.num_context, level_sampling)
    dropped = jax.random.bernoulli(dropout_key, net.action_dropout, (b,))
    normalizer = mask.sum()

    def loss_sum(params, batch):
      x0, a, lv, m, nz, drop = batch
      denoise = lambda x, lvl: net.apply({"params": params}, x, process.model_time(lvl), a,
                                         drop_actions=drop)
      return masked_loss_sum(denoise, process, x0, lv, nz, m, diffusion.object_weight,
                             diffusion.object_dilation)[0] / normalizer

    grad_fn = jax.value_and_grad(loss_sum)
    batch = (frames, actions, levels, mask, noise, dropped)
    params = state.params["params"]
    if micro == 1:
      loss, grads = grad_fn(params, batch)
    else:
      # Strided slices: sample j goes to micro-batch j % k, so that every device keeps its own
      # samples (the batch is sharded in contiguous blocks over the data axes).
      slices = jax.tree.map(
          lambda a: a.reshape((b // micro, micro) + a.shape[1:]).swapaxes(0, 1), batch)

      def accumulate(carry, piece):
        loss_piece, grad_piece = grad_fn(params, piece)
        return jax.tree.map(jnp.add, carry, (loss_piece, grad_piece)), None

      zeros = (jnp.zeros((), jnp.float32), jax.tree.map(jnp.zeros_like, params))
      (loss, grads), _ = jax.lax.scan(accumulate, zeros, slices)
    updates, opt_state = tx.update({"params": grads}, state.opt_state, state.params)
    new_params = optax.apply_updates(state.params, updates)
    new_state = state.replace(step=state.step + 1, params=new_params, opt_state=opt_state,
                              ema_params=ema_update(state.ema_params, new_params,
                                                    config.optim.ema_decay, state.step))
    metrics = {"loss": loss, "grad_norm": optax.tree.norm(grads),
               "learning_rate": schedule(state.step)}
    return new_state, metrics

  return step


def check_batch_shapes(world_model: WorldModel, frames_shape, actions_shape, mesh: Mesh,
                       micro_batches: int = 1, processes: int = 1, extra_frames: int = 0
                       ) -> None:
  """ValueError before compilation for a batch the model, the mesh, the number of
  gradient-accumulation micro-batches or the ``processes`` feeding it cannot take; its windows
  hold ``extra_frames`` more than the model's (1 with ``diffusion.self_forcing``)."""
  net = world_model.network
  if len(frames_shape) != 5 or len(actions_shape) != 3:
    raise ValueError(f"batch must hold frames [B, F, H, W, C] and actions [B, F-1, A], got "
                     f"{tuple(frames_shape)} and {tuple(actions_shape)}")
  if actions_shape[-1] != net.action_dim:
    raise ValueError(f"the data has {actions_shape[-1]}-dim actions but the model expects "
                     f"{net.action_dim} (model.action_dim)")
  if extra_frames and frames_shape[1] != net.num_frames + extra_frames:
    raise ValueError(f"with diffusion.self_forcing the windows must hold model.num_frames + 1 = "
                     f"{net.num_frames + extra_frames} frames, got {frames_shape[1]}")
  b, n = frames_shape[0], frames_shape[1] - extra_frames
  net.check_inputs(jax.ShapeDtypeStruct((b, n) + tuple(frames_shape[2:]), jnp.float32),
                   jax.ShapeDtypeStruct((b, n), jnp.float32),
                   jax.ShapeDtypeStruct((b, n - 1, actions_shape[-1]), jnp.float32))
  if actions_shape[:2] != (b, frames_shape[1] - 1):
    raise ValueError(f"actions must be [B, F-1, A] = {(b, frames_shape[1] - 1, net.action_dim)} "
                     f"for frames {tuple(frames_shape)}, got {tuple(actions_shape)}")
  parallel.check_batch_divisible(frames_shape[0], mesh, micro_batches, processes,
                                 what="global batch_size")


class ShardedTrainer:
  """Jitted, sharded ``init`` and ``step`` for one world model, config and mesh; its state is
  traced and its step compiled with attention built for ``platform`` ('gpu', 'tpu', 'cpu'; None:
  this process's own, see :func:`wmjax.nn.attention.platform_override`)."""

  def __init__(self, world_model: WorldModel, config: ml_collections.ConfigDict, mesh: Mesh,
               frame_shape: tuple[int, int, int], frames: int, platform: str | None = None):
    if world_model.network.fp8_matmuls:
      raise ConfigError("model.fp8_matmuls=True is for inference (rollouts, evaluation): wmjax "
                        "does not train through float8 rounding (that needs delayed scaling and "
                        "float8 gradients), so a model trains with "
                        "model.fp8_matmuls=False and loads with load_model(..., overrides="
                        "['model.fp8_matmuls=True']) or --config.model.fp8_matmuls=True")
    self.world_model, self.mesh, self.platform = world_model, mesh, platform
    self.frame_shape, self.frames = tuple(frame_shape), frames  # of the batches it trains on
    self.micro_batches = config.optim.grad_accum
    self.extra_frames = 1 if config.diffusion.self_forcing else 0
    self.tx = make_optimizer(config.optim)
    train_step = make_train_step(world_model, config, self.tx)

    def init(rng):
      param_rng, state_rng = jax.random.split(rng)
      return create_train_state(world_model.init(param_rng, frame_shape,
                                                 frames - self.extra_frames), self.tx,
                                state_rng)

    with attention.platform_override(platform):
      abstract = jax.eval_shape(init, jax.random.key(0))
    parallel.check_shardable(abstract, mesh)
    self.state_shardings = parallel.logical_shardings(abstract, mesh)
    self.abstract_state = abstract_with_shardings(nn.unbox(abstract), self.state_shardings)
    self.batch_sharding = parallel.batch_sharding(mesh)
    replicated = NamedSharding(mesh, PartitionSpec())
    self._init = jax.jit(lambda rng: nn.unbox(init(rng)), out_shardings=self.state_shardings)
    self._step = jax.jit(train_step,
                         in_shardings=(self.state_shardings, self.batch_sharding,
                                       self.batch_sharding),
                         out_shardings=(self.state_shardings, replicated), donate_argnums=0)
    self._compiled: dict[tuple, jax.stages.Compiled] = {}

  # All run with the mesh in context: kernels split over it by hand (splash) and the activation
  # constraints (wmjax.nn.layers.constrain) read it.

  def init(self, rng: jax.Array) -> TrainState:
    with jax.set_mesh(self.mesh):
      return self._init(rng)

  def step(self, state: TrainState, frames: Any, actions: Any):
    check_batch_shapes(self.world_model, frames.shape, actions.shape, self.mesh,
                       self.micro_batches, extra_frames=self.extra_frames)
    step = self._compiled.get(_batch_key(frames, actions), self._step)
    with jax.set_mesh(self.mesh):
      return step(state, frames, actions)

  def compile(self, state: Any, frames: Any, actions: Any) -> jax.stages.Compiled:
    """The step compiled ahead of time for this batch (arrays or ``jax.ShapeDtypeStruct``s);
    later :meth:`step` calls with the same batch shapes run it instead of compiling again.
    ``.memory_analysis()`` gives its per-device argument, output and temporary bytes; the batch
    is checked first against the model, the mesh and this job's processes."""
    check_batch_shapes(self.world_model, frames.shape, actions.shape, self.mesh,
                       self.micro_batches, jax.process_count(), self.extra_frames)
    key = _batch_key(frames, actions)
    if key not in self._compiled:
      with jax.set_mesh(self.mesh), attention.platform_override(self.platform):
        self._compiled[key] = self._step.lower(state, frames, actions).compile()
    return self._compiled[key]


def _batch_key(frames: Any, actions: Any) -> tuple:
  return (tuple(frames.shape), str(frames.dtype), tuple(actions.shape), str(actions.dtype))
