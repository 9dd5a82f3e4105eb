"""Evaluate policies inside a gridworld world model, and check the values against the true
gridworld (the WPE recipe: roll each policy out closed loop in the model, score the imagined
frames with a reward, compare the values with the simulator's).

  python examples/evaluate_policy.py WORKDIR --episodes 16 --steps 8

The policies drive the red square at a constant speed (raw action ``[vy0, vx0, vy1, vx1]`` in
pixels a step); the reward is how far right the red square ends, read from the last frame.
"""

import argparse

import jax
import numpy as np

from wmjax.data.sources import ArrayRecordEpisodes, dataset_dir
from wmjax.env import WorldModelEnv
from wmjax.eval.policy_eval import agreement, env_episodes, episode_returns, policy_value
from wmjax.eval.trajectories import whole_episodes
from wmjax.model import load_model
from wmjax.tasks.gridworld import dataset as gridworld
from wmjax.tasks.gridworld.metrics import color_centroids

SPEEDS = (2.0, 1.0, 0.0, -1.0)  # the red square's x speed under each policy


def red_x(frames, instruction=None):
  """The reward: the red square's x centre in the last frame, over the frame's width [B]."""
  centres, found = color_centroids(frames[:, -1], gridworld.COLORS[:1])
  return np.where(found[:, 0], centres[:, 0, 1] / frames.shape[-2], 0.0)


def constant_speed(speed: float, action_dim: int):
  def policy(frames, key):  # newest frames [B, c, H, W, 3] -> raw actions [B, 1, A]
    action = np.zeros((len(frames), 1, action_dim), np.float32)
    action[:, :, 1] = speed
    return action
  return policy


def simulate(config: gridworld.GridworldConfig, centres: np.ndarray, speed: float, steps: int):
  """The true gridworld: the squares from ``centres [B, n, 2]``, the red one moved at ``speed``."""
  half = config.square_size / 2
  velocity = np.zeros_like(centres)
  velocity[:, 0, 1] = speed
  for _ in range(steps):
    centres = np.clip(centres + velocity, half, config.image_size - half)
  return np.stack([gridworld.render(c, config) for c in centres])[:, None]  # [B, 1, H, W, 3]


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("workdir")
  parser.add_argument("--episodes", type=int, default=16)
  parser.add_argument("--steps", type=int, default=8)
  args = parser.parse_args(argv)

  model = load_model(args.workdir)
  data = model.config.data
  episodes = ArrayRecordEpisodes(dataset_dir(data), data.eval_split)
  starts = whole_episodes(episodes, None, min_length=1, limit=args.episodes)
  first_frames = np.stack([w["frames"][:1] for w in starts])               # [B, 1, H, W, 3]
  first_centres = np.stack([w["square_positions"][0] for w in starts])     # [B, n, 2]
  env = WorldModelEnv.from_model(model)
  world_config = gridworld.GridworldConfig.from_saved(data.gridworld)
  imagined, true = [], []
  for speed in SPEEDS:
    rollout = env_episodes(env, constant_speed(speed, env.action_dim), first_frames, args.steps,
                           jax.random.key(0))
    imagined.append(policy_value(episode_returns(rollout["frames"], red_x)))
    true.append(policy_value(red_x(simulate(world_config, first_centres, speed, args.steps))))
  for speed, m, t in zip(SPEEDS, imagined, true):
    print(f"speed {speed:+.0f}: world model {m.mean:.3f} ± {m.stderr:.3f}, "
          f"true {t.mean:.3f} ± {t.stderr:.3f}")
  result = agreement([t.mean for t in true], [m.mean for m in imagined])
  print(f"Pearson {result['pearson']:.3f}, ranking preserved: {bool(result['ranking_preserved'])}")
  return result


if __name__ == "__main__":
  main()
