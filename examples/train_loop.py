"""Your own training loop: the library's data pipeline and diffusion loss under an optax
optimiser you choose, in a dozen lines (``wmjax train`` adds checkpoints, EMA, evaluation,
sharding and resumption; see ``wmjax.train``).

  python examples/train_loop.py --config configs/gridworld.py --steps 200 \\
      --config.data.data_dir=~/tensorflow_datasets
"""

import argparse

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax

from wmjax.config import load_config, split_overrides
from wmjax.data.pipeline import WindowSource, frames_to_float, training_pipeline
from wmjax.data.sources import open_dataset
from wmjax.diffusion import LevelSampling, diffusion_loss
from wmjax.model import WorldModel


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--config", default="configs/gridworld.py")
  parser.add_argument("--steps", type=int, default=200)
  parser.add_argument("--learning_rate", type=float, default=1e-3)
  args, rest = parser.parse_known_args(argv)
  overrides, unknown = split_overrides(rest)                  # --config.KEY=VALUE overrides
  if unknown:
    parser.error(f"unrecognized arguments: {' '.join(unknown)}")
  config = load_config(args.config, overrides)

  dataset = open_dataset(config.data)                         # generated if missing (gridworld)
  episodes = dataset.split(config.data.train_split)
  windows = WindowSource(episodes, config.data.frames, config.data.train_stride,
                         dataset.resolution(episodes.spec))
  batches = iter(training_pipeline([windows], [dataset.train_stats()],
                                   batch_size=config.batch_size, seed=config.seed))

  wm = WorldModel.from_config(config)
  params = nn.unbox(wm.init(jax.random.key(config.seed), config.frame_shape, config.data.frames))
  optimizer = optax.chain(optax.clip_by_global_norm(1.0), optax.adamw(args.learning_rate))
  opt_state = optimizer.init(params)
  levels = LevelSampling.from_config(config.diffusion)

  def loss_fn(params, frames, actions, rng):
    # the network takes model times; diffusion_loss hands the process's levels
    denoise = lambda x, lvl: wm.network.apply(params, x, wm.process.model_time(lvl), actions)
    loss, _ = diffusion_loss(denoise, wm.process, frames, rng, config.diffusion.regime,
                             config.diffusion.num_context, levels)
    return loss

  @jax.jit
  def step(params, opt_state, frames, actions, rng):
    loss, grads = jax.value_and_grad(loss_fn)(params, frames, actions, rng)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, loss

  losses = []
  for k in range(args.steps):
    batch = next(batches)                                     # frames uint8, actions normalised
    frames = jnp.asarray(frames_to_float(batch)["frames"])    # [B, T, H, W, 3] in [-1, 1]
    params, opt_state, loss = step(params, opt_state, frames, jnp.asarray(batch["actions"]),
                                   jax.random.key(k))
    losses.append(float(loss))
    if k % 50 == 0 or k == args.steps - 1:
      print(f"step {k}: loss {losses[-1]:.4f}")
  return losses


if __name__ == "__main__":
  main()
