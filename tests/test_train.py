"""Sharded training: the same parameters on any mesh, and errors before compilation."""

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import perturbed, tiny_config
from wmjax.codecs import PixelCodec
from wmjax.eval.trajectories import Trajectories
from wmjax.parallel import make_mesh
from wmjax.model import WorldModel
from wmjax.rollout import sample_block
from wmjax.train.loop import validation_loss
from wmjax.train.self_forcing import check_self_forcing, self_forced_windows
from wmjax.train.step import ShardedTrainer

pytestmark = pytest.mark.unit

OVERRIDES = ("model.in_channels=3", "model.action_dim=4", "model.hidden_size=32",
             "model.num_heads=4", "optim.grad_clip=0.1")


def _batch(seed=0, batch=8, frames=4):
  k1, k2 = jax.random.split(jax.random.key(seed))
  return (jax.random.uniform(k1, (batch, frames, 8, 8, 3), minval=-1, maxval=1),
          jax.random.normal(k2, (batch, frames - 1, 4)))


def _train(mesh_shape, devices=None, steps=3):
  config = tiny_config("gridworld.py", *OVERRIDES)
  mesh = make_mesh(mesh_shape, devices)
  trainer = ShardedTrainer(WorldModel.from_config(config), config, mesh, (8, 8, 3), 4)
  state = trainer.init(jax.random.key(0))
  for i in range(steps):
    state, metrics = trainer.step(state, *_batch(i))
  return state, metrics


@pytest.mark.slow
def test_sharded_equals_unsharded():
  """Data and FSDP axes together (the tensor axis: the splash test below): the same loss and
  parameters as one device, with the weights really split over the FSDP axis."""
  reference, ref_metrics = _train((1, 1, 1), devices=jax.devices()[:1])
  state, metrics = _train((2, 4, 1))
  assert int(state.step) == 3
  np.testing.assert_allclose(metrics["loss"], ref_metrics["loss"], rtol=1e-5)
  for a, b in zip(jax.tree.leaves(state.params), jax.tree.leaves(reference.params)):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6)
  for a, b in zip(jax.tree.leaves(state.ema_params), jax.tree.leaves(reference.ema_params)):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6)
  kernel = state.params["params"]["blocks"]["layers"]["spatial"]["mlp"]["fc1"]["kernel"]
  assert kernel.sharding.spec == jax.sharding.PartitionSpec(None, "fsdp", "tensor")
  assert kernel.addressable_shards[0].data.shape[1] == 32 // 4  # really sharded


def test_bad_batches_fail_before_compilation():
  config = tiny_config("gridworld.py", *OVERRIDES)
  trainer = ShardedTrainer(WorldModel.from_config(config), config, make_mesh((2, 4, 1)),
                           (8, 8, 3), 4)
  state = trainer.init(jax.random.key(0))
  frames, actions = _batch()
  with pytest.raises(ValueError, match="the data has 7-dim actions but the model expects 4"):
    trainer.step(state, frames, jnp.zeros((8, 3, 7)))
  with pytest.raises(ValueError, match="global batch_size 6 is not divisible by the data-parallel size 8"):
    trainer.step(state, frames[:6], actions[:6])
  with pytest.raises(ValueError, match="mesh \\(3, 1, 1\\) needs 3 devices, 8 are available"):
    make_mesh((3, 1, 1))
  with pytest.raises(ValueError, match=r"'heads' axis \(model.num_heads\), which the mesh's tensor "
                     r"axis \(8\) does not divide; choose config.mesh"):
    ShardedTrainer(WorldModel.from_config(config), config, make_mesh((1, 1, 8)), (8, 8, 3), 4)


@pytest.mark.slow
def test_memory_estimate_moves_with_remat_dtype_batch_and_sharding():
  from wmjax.train.memory import estimate

  def report(*overrides, devices=8):
    config = tiny_config("irasim.py:S", "batch_size=16", "model.depth=16", *overrides)
    return estimate(config, WorldModel.from_config(config), devices)

  plain = report()
  assert plain["parameters"] > 0 and plain["mesh"] == [8, 1, 1] and plain["local_batch"] == 2
  activations = [report(f"model.remat='{p}'")["activations_gib"]
                 for p in ("none", "dots_elementwise", "dots_attention", "dots", "full")]
  assert activations == sorted(activations, reverse=True) and activations[-1] < activations[0] / 4
  assert report("model.dtype='bfloat16'")["activations_gib"] < plain["activations_gib"]
  assert report("batch_size=32")["activations_gib"] > 1.9 * plain["activations_gib"]
  fsdp = report("mesh=(2, 4, 1)")
  assert abs(fsdp["state_gib"] * 4 - plain["state_gib"]) < 1e-9
  assert abs(plain["state_gib"] - 16 * plain["parameters"] / 1024 ** 3) < 1e-9


@pytest.mark.slow
def test_sharded_training_with_splash_attention_equals_xla():
  """The splash kernel split over an (4, 1, 2) mesh by hand (shard_map) in the jitted, rematted
  train step: the same loss and parameters as XLA attention. 16x16 frames of 1x1 patches make
  256-token spatial sequences, so the kernel really runs (Pallas interpret mode on CPU)."""
  def train(backend):
    config = tiny_config("gridworld.py", *OVERRIDES, "model.patch_size=1", "model.remat='dots'",
                         f"model.attention_impl={backend!r}")
    trainer = ShardedTrainer(WorldModel.from_config(config), config, make_mesh((4, 1, 2)),
                             (16, 16, 3), 3)
    state = trainer.init(jax.random.key(0))
    frames = jax.random.uniform(jax.random.key(1), (8, 3, 16, 16, 3), minval=-1, maxval=1)
    actions = jax.random.normal(jax.random.key(2), (8, 2, 4))
    return trainer.step(state, frames, actions)

  state, metrics = train("splash")
  ref_state, ref_metrics = train("xla")
  np.testing.assert_allclose(metrics["loss"], ref_metrics["loss"], rtol=1e-5)
  for a, b in zip(jax.tree.leaves(state.params), jax.tree.leaves(ref_state.params)):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-5)


@pytest.mark.slow
def test_compiled_step_is_reused_and_matches_the_jitted_step():
  """``ShardedTrainer.compile`` (what a memory check compiles) runs the same step as ``step``,
  and later steps with that batch shape run the compiled program instead of compiling again."""
  config = tiny_config("gridworld.py", *OVERRIDES)
  trainer = ShardedTrainer(WorldModel.from_config(config), config, make_mesh((2, 4, 1)),
                           (8, 8, 3), 4)
  frames, actions = _batch()
  reference, ref_metrics = trainer.step(trainer.init(jax.random.key(0)), frames, actions)
  state = trainer.init(jax.random.key(0))
  compiled = trainer.compile(state, frames, actions)
  assert compiled.memory_analysis().temp_size_in_bytes > 0
  assert trainer.compile(state, frames, actions) is compiled
  state, metrics = trainer.step(state, frames, actions)
  np.testing.assert_allclose(metrics["loss"], ref_metrics["loss"], rtol=1e-6)
  for a, b in zip(jax.tree.leaves(state.params), jax.tree.leaves(reference.params)):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6)


@pytest.mark.slow
def test_gradient_accumulation_equals_the_whole_batch():
  """optim.grad_accum = 4 cuts the batch of 8 into 4 micro-batches inside the step: same loss,
  gradient norm and parameters as the whole batch (float rounding aside), on a sharded mesh."""
  results = []
  for micro in (1, 4):
    config = tiny_config("gridworld.py", *OVERRIDES, f"optim.grad_accum={micro}")
    trainer = ShardedTrainer(WorldModel.from_config(config), config, make_mesh((2, 1, 1),
                             jax.devices()[:2]), (8, 8, 3), 4)
    state = trainer.init(jax.random.key(0))
    for i in range(2):
      state, metrics = trainer.step(state, *_batch(i))
    results.append((state, metrics))
  (whole, whole_metrics), (accumulated, metrics) = results
  np.testing.assert_allclose(metrics["loss"], whole_metrics["loss"], rtol=1e-5)
  np.testing.assert_allclose(metrics["grad_norm"], whole_metrics["grad_norm"], rtol=1e-4)
  for a, b in zip(jax.tree.leaves(accumulated.params), jax.tree.leaves(whole.params)):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6)
  with pytest.raises(ValueError, match=r"not divisible by the data-parallel size 2 x 4 micro"):
    trainer.step(accumulated, *_batch(0, batch=4))


SELF_FORCED = OVERRIDES + ("model.num_frames=4", "data.frames=5", "diffusion.self_forcing=0.5",
                           "sampling.num_steps=2")


def test_self_forced_windows_replace_the_chosen_samples_last_context_frame():
  config = tiny_config("gridworld.py", *SELF_FORCED, "diffusion.num_context=2")
  world_model = WorldModel.from_config(config)
  params = perturbed(world_model.init(jax.random.key(0), (8, 8, 3)), jax.random.key(1))
  frames, actions = _batch(batch=4, frames=5)
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
  frames, actions = _batch(frames=5)
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
    trainer.step(state, *_batch(frames=4))


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
  plain_config = tiny_config("gridworld.py", *OVERRIDES, "model.num_frames=4", "data.frames=4")
  world_model = WorldModel.from_config(config)
  params = perturbed(world_model.init(jax.random.key(0), (8, 8, 3)), jax.random.key(1))
  frames, actions = _batch(batch=4, frames=5)
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
