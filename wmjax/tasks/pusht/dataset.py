"""Push-T episodes from the gym-pusht simulator as an RLDS TFDS dataset in ArrayRecord.

Each episode starts with the T near its goal (centre within ``max_offset`` px, angle within
``max_angle`` rad, see :func:`.simulator.random_initial_states`) and the agent elsewhere, and is
driven by the frame-based :class:`.simulator.PushPolicy` with Gaussian action noise; episodes
cycle through ``noise_levels`` (WPE collects with 0.1 / 0.2 / 0.5), so the data holds good
pushes, poor ones and failures. The action is the agent's target ``(x, y)`` in ``[0, 512]``
(step ``t``'s action leads to frame ``t + 1``; the last step repeats the agent's position).
Every step stores the simulator's state (``observation/state``: agent x, y, block x, y, angle as
gym-pusht's ``state`` observation, the block's body origin; :func:`.simulator.reset_state` turns
it into the simulator's ``reset_to_state``),
``observation/coverage``, ``observation/success`` (coverage > 0.95) and the episode's
``observation/policy_noise``; the reward is gym-pusht's ``clip(coverage / 0.95, 0, 1)``.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import tensorflow_datasets as tfds

from wmjax.data import oxe, synthetic
from wmjax.tasks.pusht import simulator

INSTRUCTION = "push the T-shaped block onto the green T"

oxe.register(oxe.DatasetSpec("pusht", "wmjax", extra_keys=(
    "observation/state", "observation/coverage", "observation/success",
    "observation/policy_noise")))


@dataclasses.dataclass(frozen=True)
class PushTConfig:
  """Defaults fit CPU training: 48x48 renders, 40-step episodes (4 s at 10 Hz)."""

  image_size: int = 48
  episode_length: int = 40
  train_episodes: int = 640
  test_episodes: int = 64
  noise_levels: tuple[float, ...] = (0.0, 0.1, 0.2, 0.5)
  chunk: int = 4
  max_offset: float = 90.0
  max_angle: float = 0.5
  batch: int = 32
  seed: int = 0

  @classmethod
  def from_dict(cls, values) -> "PushTConfig":
    """From a config section."""
    return cls(**dict(values))

  def __post_init__(self):
    object.__setattr__(self, "noise_levels", tuple(float(n) for n in self.noise_levels))
    if self.image_size < 8 or self.episode_length < 2 or not self.noise_levels:
      raise ValueError(f"need image_size >= 8, episode_length >= 2 and noise levels, got "
                       f"{self.image_size}, {self.episode_length}, {self.noise_levels}")
    if min(self.noise_levels) < 0 or self.chunk < 1 or self.batch < 1:
      raise ValueError(f"noise levels must be >= 0 and chunk, batch >= 1, got "
                       f"{self.noise_levels}, {self.chunk}, {self.batch}")

  @property
  def name(self) -> str:
    noise = "-".join(f"{n:g}" for n in self.noise_levels)
    return (f"s{self.image_size}_l{self.episode_length}_e{self.train_episodes}-"
            f"{self.test_episodes}_n{noise}_c{self.chunk}_o{self.max_offset:g}"
            f"_a{self.max_angle:g}_seed{self.seed}")


def _draws(config: PushTConfig, num_episodes: int, rng: np.random.Generator):
  """What ``rng`` decides of ``num_episodes`` episodes, ``config.batch`` at a time: per batch the
  noise levels ``[b]`` (cycling through ``config.noise_levels``), the start states ``[b, 5]`` and
  the simulation's key seed."""
  levels = config.noise_levels
  for first in range(0, num_episodes, config.batch):
    count = min(config.batch, num_episodes - first)
    noise = np.array([levels[(first + i) % len(levels)] for i in range(count)], np.float32)
    states = simulator.random_initial_states(rng, count, max_offset=config.max_offset,
                                             max_angle=config.max_angle)
    yield noise, states, int(rng.integers(2**31))


def collect(config: PushTConfig, num_episodes: int, rng: np.random.Generator):
  """Simulate ``num_episodes`` episodes, ``config.batch`` at a time, cycling through the noise
  levels; yields :class:`wmjax.data.synthetic.GeneratedEpisode`."""
  expert = simulator.PushPolicy(chunk=config.chunk)
  for noise, states, seed in _draws(config, num_episodes, rng):

    def policy(frames, key, noise=noise):  # the expert with each episode's own noise level
      return expert.act(frames, key, noise)

    run = simulator.simulate_policy(policy, states, config.episode_length - 1,
                                    image_size=config.image_size, key=jax.random.key(seed))
    for i in range(len(states)):
      actions = np.concatenate([run["actions"][i], run["state"][i, -1:, :2]])  # last: stay
      coverage = run["coverage"][i]
      yield synthetic.GeneratedEpisode(
          images=run["frames"][i], actions=actions.astype(np.float32), instruction=INSTRUCTION,
          rewards=np.clip(coverage / simulator.SUCCESS_COVERAGE, 0, 1).astype(np.float32),
          observations={"state": run["state"][i], "coverage": coverage,
                        "success": coverage > simulator.SUCCESS_COVERAGE,
                        "policy_noise": np.full(len(coverage), noise[i], np.float32)})


class PushT(synthetic.SyntheticBuilder):
  """Push-T episodes from gym-pusht driven by a scripted pusher at several noise levels."""

  name = "pusht"
  VERSION = tfds.core.Version("1.0.0")
  RELEASE_NOTES = {"1.0.0": "Scripted pushes near the goal with per-step coverage and state."}

  def action_dim(self) -> int:
    return 2

  def observation_features(self):
    scalar = tfds.features.Scalar(dtype=np.float32)
    return {"state": tfds.features.Tensor(shape=(5,), dtype=np.float32), "coverage": scalar,
            "success": np.bool_, "policy_noise": scalar}

  def episodes(self, count, rng):
    return collect(self.params, count, rng)

  @classmethod
  def check_can_write(cls):
    simulator.check_installed()

  @classmethod
  def start_states(cls, params, split):
    """``reset_to_state`` vectors ``[N, 5]`` every episode of ``split`` started from."""
    draws = _draws(params, cls.episode_count(params, split), synthetic.stream(params.seed, split))
    return np.concatenate([states for _, states, _ in draws])


def prepare(data_dir: str, config: PushTConfig = PushTConfig()) -> str:
  """Simulate and write the dataset under ``data_dir`` (once); returns the builder directory."""
  return synthetic.prepare(PushT, data_dir, config)
