"""Sharded training: the same parameters on any mesh, and errors before compilation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import TRAIN_OVERRIDES, tiny_config, train_batch
from wmjax.parallel import make_mesh
from wmjax.model import WorldModel
from wmjax.train.step import ShardedTrainer

pytestmark = pytest.mark.unit


def _train(mesh_shape, devices=None, steps=3):
  config = tiny_config("gridworld.py", *TRAIN_OVERRIDES)
  mesh = make_mesh(mesh_shape, devices)
  trainer = ShardedTrainer(WorldModel.from_config(config), config, mesh, (8, 8, 3), 4)
  state = trainer.init(jax.random.key(0))
  for i in range(steps):
    state, metrics = trainer.step(state, *train_batch(i))
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
  config = tiny_config("gridworld.py", *TRAIN_OVERRIDES)
  trainer = ShardedTrainer(WorldModel.from_config(config), config, make_mesh((2, 4, 1)),
                           (8, 8, 3), 4)
  state = trainer.init(jax.random.key(0))
  frames, actions = train_batch()
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
    config = tiny_config("gridworld.py", *TRAIN_OVERRIDES, "model.patch_size=1",
                         "model.remat='dots'", f"model.attention_impl={backend!r}")
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
  config = tiny_config("gridworld.py", *TRAIN_OVERRIDES)
  trainer = ShardedTrainer(WorldModel.from_config(config), config, make_mesh((2, 4, 1)),
                           (8, 8, 3), 4)
  frames, actions = train_batch()
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
    config = tiny_config("gridworld.py", *TRAIN_OVERRIDES, f"optim.grad_accum={micro}")
    trainer = ShardedTrainer(WorldModel.from_config(config), config, make_mesh((2, 1, 1),
                             jax.devices()[:2]), (8, 8, 3), 4)
    state = trainer.init(jax.random.key(0))
    for i in range(2):
      state, metrics = trainer.step(state, *train_batch(i))
    results.append((state, metrics))
  (whole, whole_metrics), (accumulated, metrics) = results
  np.testing.assert_allclose(metrics["loss"], whole_metrics["loss"], rtol=1e-5)
  np.testing.assert_allclose(metrics["grad_norm"], whole_metrics["grad_norm"], rtol=1e-4)
  for a, b in zip(jax.tree.leaves(accumulated.params), jax.tree.leaves(whole.params)):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6)
  with pytest.raises(ValueError, match=r"not divisible by the data-parallel size 2 x 4 micro"):
    trainer.step(accumulated, *train_batch(0, batch=4))

