"""Self-forcing (``diffusion.self_forcing``): windows one frame longer whose last context frame
the model samples itself, from the train step's start on, and the settings it refuses."""

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import TRAIN_OVERRIDES, perturbed, tiny_config, train_batch
from wmjax.codecs import PixelCodec
from wmjax.eval.trajectories import Trajectories
from wmjax.model import WorldModel
from wmjax.parallel import make_mesh
from wmjax.rollout import sample_block
from wmjax.train.loop import validation_loss
from wmjax.train.self_forcing import check_self_forcing, self_forced_windows
from wmjax.train.step import ShardedTrainer

pytestmark = pytest.mark.unit

SELF_FORCED = TRAIN_OVERRIDES + ("model.num_frames=4", "data.frames=5",
                                 "diffusion.self_forcing=0.5", "sampling.num_steps=2")


def test_self_forced_windows_replace_the_chosen_samples_last_context_frame():
  config = tiny_config("gridworld.py", *SELF_FORCED, "diffusion.num_context=2")
  world_model = WorldModel.from_config(config)
  params = perturbed(world_model.init(jax.random.key(0), (8, 8, 3)), jax.random.key(1))
  frames, actions = train_batch(batch=4, frames=5)
  key = jax.random.key(2)
  windows, window_actions = jax.jit(self_forced_windows, static_argnums=(0, 4, 5))(
      world_model, params, frames, actions, 0.5, 2, key)
  assert windows.shape == (4, 4, 8, 8, 3) and window_actions.shape == (4, 3, 4)
  np.testing.assert_array_equal(window_actions, actions[:, 1:])
  np.testing.assert_array_equal(windows[1::2], frames[1::2, 1:])  # samples 1 and 3: the data's
  for frame in (0, 2, 3):
    np.testing.assert_array_equal(windows[::2, frame], frames[::2, frame + 1])
  generated = sample_block(world_model, params, frames[::2, :2], actions[::2, :2], key)
  np.testing.assert_allclose(windows[::2, 1], generated[:, 0], rtol=1e-5, atol=1e-5)
  assert np.abs(windows[::2, 1] - frames[::2, 2]).mean() > 0.1  # the model's, not the data's


def test_self_forcing_starts_at_its_step_on_windows_one_frame_longer():
  """Before ``self_forcing_start`` a step trains on the data's frames 1..N, so the window's first
  frame changes nothing; from it on the generated context frame is sampled from it."""
  config = tiny_config("gridworld.py", *SELF_FORCED, "diffusion.self_forcing_start=1")
  trainer = ShardedTrainer(WorldModel.from_config(config), config,
                           make_mesh((1, 1, 1), jax.devices()[:1]), (8, 8, 3), 5)
  state = trainer.init(jax.random.key(0))
  weights = perturbed(state.params, jax.random.key(1))  # a fresh model's output ignores its input
  state = jax.device_put(state.replace(params=weights, ema_params=jax.tree.map(jnp.copy, weights)),
                         trainer.state_shardings)
  frames, actions = train_batch(frames=5)
  other_first = frames.at[:, 0].set(-frames[:, 0])
  losses = []
  for _ in range(2):  # steps 0 and 1
    copy = jax.tree.map(jnp.copy, state)  # the step donates its state
    _, other = trainer.step(copy, other_first, actions)
    state, metrics = trainer.step(state, frames, actions)
    losses.append((float(metrics["loss"]), float(other["loss"])))
  assert losses[0][0] == losses[0][1]
  assert np.isfinite(losses[1][0]) and abs(losses[1][0] - losses[1][1]) > 1e-4 * losses[1][0]
  with pytest.raises(ValueError, match="windows must hold model.num_frames \\+ 1 = 5 frames, got 4"):
    trainer.step(state, *train_batch(frames=4))


@pytest.mark.parametrize("override, message", [
    ("data.frames=4", "data.frames = model.num_frames \\+ 1 = 5, got data.frames=4"),
    ("diffusion.self_forcing=0.375", "gives 3 samples with a generated frame; it must be a whole "
                                     "divisor of the batch"),
    ("diffusion.regime='per_frame'", "needs clean context frames to replace"),
    ("diffusion.self_forcing=1.5", "in \\(0, 1\\]; got 1.5"),
    ("diffusion.self_forcing_start=-1", "self_forcing_start is a train step, >= 0; got -1"),
])
def test_self_forcing_settings_the_data_cannot_serve_are_refused(override, message):
  config = tiny_config("gridworld.py", *SELF_FORCED, "batch_size=8", override)
  with pytest.raises(ValueError, match=message):
    check_self_forcing(config)


def test_self_forced_runs_validate_on_the_last_model_window_of_their_longer_windows():
  """The validation loss of a self-forced run is the plain loss on its windows' last
  ``model.num_frames`` frames: the data's frames, no generated one."""
  config = tiny_config("gridworld.py", *SELF_FORCED)
  plain_config = tiny_config("gridworld.py", *TRAIN_OVERRIDES, "model.num_frames=4",
                             "data.frames=4")
  world_model = WorldModel.from_config(config)
  params = perturbed(world_model.init(jax.random.key(0), (8, 8, 3)), jax.random.key(1))
  frames, actions = train_batch(batch=4, frames=5)
  uint8 = np.asarray((frames + 1) * 127.5, np.uint8)
  held_out = Trajectories(uint8, np.asarray(actions), np.full(4, 5), {}, np.arange(4),
                          np.zeros(4, int))
  shorter = Trajectories(uint8[:, 1:], np.asarray(actions[:, 1:]), np.full(4, 4), {},
                         np.arange(4), np.zeros(4, int))

  def loss(config, trajectories):
    context = SimpleNamespace(config=config, world_model=world_model,
                              data=SimpleNamespace(codec=PixelCodec()))
    return validation_loss(context, params, trajectories, jax.random.key(3), jax.random.key(4))

  np.testing.assert_allclose(loss(config, held_out), loss(plain_config, shorter), rtol=1e-6)


@pytest.mark.parametrize("regime", ["irasim", "autoregressive"])
def test_self_forcing_accepts_every_regime_with_clean_context_frames(regime):
  config = tiny_config("gridworld.py", *SELF_FORCED, "batch_size=8", f"diffusion.regime={regime!r}",
                       "diffusion.num_context=2")
  check_self_forcing(config)  # no error: the context frames it replaces are clean
