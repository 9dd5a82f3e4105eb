"""Step a world model like a simulator: ``WorldModelEnv`` takes raw action chunks and returns
the new frames, as a gymnasium environment would (here a random policy, 8 chunks).

  python examples/closed_loop.py WORKDIR --frames first_frames.npy --steps 8

``first_frames.npy``: uint8 ``[B, c0, H, W, 3]`` with ``1 <= c0 <=`` the model's context.
"""

import argparse

import numpy as np

from wmjax.env import WorldModelEnv
from wmjax.model import load_model


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("workdir")
  parser.add_argument("--frames", required=True)
  parser.add_argument("--steps", type=int, default=8)
  parser.add_argument("--seed", type=int, default=0)
  args = parser.parse_args(argv)

  model = load_model(args.workdir)
  env = WorldModelEnv.from_model(model, seed=args.seed)   # the config's context and horizon
  stats = model.action_stats                              # raw actions' mean and spread
  rng = np.random.default_rng(args.seed)
  obs, info = env.reset(np.load(args.frames))
  for _ in range(args.steps):
    chunk = rng.normal(stats.mean, stats.std, (env.num_envs, env.horizon, env.action_dim))
    obs, reward, terminated, truncated, info = env.step(chunk.astype(np.float32))
  video = env.video()                                     # [B, c0 + steps * horizon, H, W, 3]
  print(f"{env.num_envs} environments, {info['frames']} frames each")
  return video


if __name__ == "__main__":
  main()
