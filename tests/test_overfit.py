"""Model, objective and sampler fit together: a tiny model memorises one clip of a moving square."""

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from conftest import tiny_config
from wmjax.diffusion import diffusion_loss
from wmjax.model import WorldModel
from wmjax.rollout import rollout

pytestmark = [pytest.mark.integration, pytest.mark.slow]

OPTIMISED = {"xla_backend_optimization_level": 2}  # XLA's default


def moving_square_clip(frames=6, size=16, square=4, seed=0):
  """One clip ``[1, T, S, S, 3]`` in [-1, 1] of a magenta square moved by 2-D actions ``[1, T-1, 2]``."""
  rng = np.random.default_rng(seed)
  pos = np.array([2, 3])
  video, actions = [], []
  for t in range(frames):
    frame = -np.ones((size, size, 3), np.float32)
    frame[pos[0]:pos[0] + square, pos[1]:pos[1] + square] = (1, -1, 1)
    video.append(frame)
    if t < frames - 1:
      step = rng.integers(-2, 3, 2)
      pos = np.clip(pos + step, 0, size - square)
      actions.append(step / 2)
  return jnp.asarray(np.stack(video))[None], jnp.asarray(np.stack(actions), jnp.float32)[None]


def test_tiny_model_overfits_a_moving_square():
  config = tiny_config("wpe_600m.py", "model.in_channels=3", "model.action_dim=2",
                       "model.hidden_size=64", "model.num_heads=4", "model.action_dropout=0.0",
                       "sampling.num_steps=20")
  wm = WorldModel.from_config(config)
  clip, actions = moving_square_clip()
  # a batch of 4 copies (4 noise draws a step): 200 steps of 8 copies took twice as long and fit
  # no better (loss / 36 against / 25, rollout at 0.08 against 0.15 of copying the first frame)
  batch, batch_actions = jnp.tile(clip, (4, 1, 1, 1, 1)), jnp.tile(actions, (4, 1, 1))
  params = nn.unbox(wm.init(jax.random.key(0), clip.shape[2:], frames=clip.shape[1]))
  optimizer = optax.adam(3e-3)

  def loss_fn(p, rng):
    denoise = lambda x, levels: wm.network.apply(p, x, wm.process.model_time(levels), batch_actions)
    return diffusion_loss(denoise, wm.process, batch, rng, config.diffusion.regime)[0]

  # 200 steps run here: compiled with XLA's backend optimisations, which tests/conftest.py turns
  # off for the suite's many programs that run once or twice.
  @functools.partial(jax.jit, compiler_options=OPTIMISED)
  def train_step(p, opt_state, rng):
    loss, grads = jax.value_and_grad(loss_fn)(p, rng)
    updates, opt_state = optimizer.update(grads, opt_state, p)
    return optax.apply_updates(p, updates), opt_state, loss

  eval_keys = jax.random.split(jax.random.key(123), 32)  # the same noise draws before and after
  eval_loss = jax.jit(lambda p: jax.vmap(lambda k: loss_fn(p, k))(eval_keys).mean())
  initial = float(eval_loss(params))
  opt_state = optimizer.init(params)
  for i in range(200):
    params, opt_state, _ = train_step(params, opt_state, jax.random.key(i))
  final = float(eval_loss(params))
  assert final < initial / 10, (initial, final)

  video = rollout(wm, params, clip[:, :1], actions, jax.random.key(0), horizon=5)
  model_mse = float(jnp.mean((video[:, 1:] - clip[:, 1:]) ** 2))
  copy_last_mse = float(jnp.mean((clip[:, :1] - clip[:, 1:]) ** 2))
  assert model_mse < 0.25 * copy_last_mse, (model_mse, copy_last_mse)
