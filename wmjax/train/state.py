"""Train state (params, EMA params, optimiser state, step, RNG) and the AdamW optimiser."""

from __future__ import annotations

from typing import Any

import flax
import jax
import jax.numpy as jnp
import ml_collections
import optax

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
