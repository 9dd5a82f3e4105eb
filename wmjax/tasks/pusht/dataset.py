"""Push-T episodes from the gym-pusht simulator as an RLDS TFDS dataset in ArrayRecord.

Each episode starts with the T near its goal (centre within ``max_offset`` px, angle within
``max_angle`` rad, see :func:`.simulator.random_initial_states`) and the agent elsewhere, and is
driven by the frame-based :class:`.simulator.PushPolicy` with Gaussian action noise; episodes
cycle through ``noise_levels`` (WPE collects with 0.1 / 0.2 / 0.5), so the data holds good
pushes, poor ones and failures. The action is the agent's target ``(x, y)`` in ``[0, 512]``
(step ``t``'s action leads to frame ``t + 1``; the last step repeats the agent's position).
``mix`` sets the fractions of three kinds of episode: the scripted pusher (the default, every
episode), a random agent (:class:`RandomAgent`: every chunk a new target within ``random_reach``
px of the T's centre, so it touches the T from every side, or passes it by) and an idle agent
(its target is where it starts: nothing moves). The kinds are interleaved by a deterministic
weighted round robin (:func:`episode_kinds`), draw nothing from the random stream and leave the
start states where they were; the noise levels cycle over the scripted episodes alone.
Every step stores the simulator's state (``observation/state``: agent x, y, block x, y, angle as
gym-pusht's ``state`` observation, the block's body origin; :func:`.simulator.reset_state` turns
it into the simulator's ``reset_to_state``),
``observation/coverage``, ``observation/success`` (coverage > 0.95) and the episode's
``observation/policy_noise`` (the scripted pusher's noise level; :data:`RANDOM_AGENT` = -1 for a
random agent, :data:`IDLE_AGENT` = -2 for an idle one); the reward is gym-pusht's
``clip(coverage / 0.95, 0, 1)``.
"""

from __future__ import annotations

import dataclasses
import itertools
import multiprocessing
from concurrent import futures

import jax
import jax.numpy as jnp
import numpy as np
import tensorflow_datasets as tfds

from wmjax.data import oxe, synthetic
from wmjax.data.synthetic import episode_kinds
from wmjax.tasks.pusht import simulator

INSTRUCTION = "push the T-shaped block onto the green T"
KINDS = ("push", "random", "idle")  # the episode kinds of ``PushTConfig.mix``, in its order
# ``observation/policy_noise`` of the episodes that are not scripted pushes
RANDOM_AGENT, IDLE_AGENT = -1.0, -2.0

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
  mix: tuple[float, ...] = (1.0, 0.0, 0.0)  # fractions of scripted push / random / idle agents
  random_reach: float = 160.0
  # control steps (0.1 s) each action is held for, one frame per action: with 4 and chunk 1, a
  # frame per decision of the default's 4-step chunks (episode_length counts frames)
  action_repeat: int = 1

  @classmethod
  def from_dict(cls, values) -> "PushTConfig":
    """From a config section."""
    return cls(**dict(values))

  def __post_init__(self):
    object.__setattr__(self, "noise_levels", tuple(float(n) for n in self.noise_levels))
    object.__setattr__(self, "mix", tuple(float(f) for f in self.mix))
    if (len(self.mix) != len(KINDS) or min(self.mix) < 0 or abs(sum(self.mix) - 1) > 1e-6
        or self.random_reach <= 0):
      raise ValueError(f"mix must be {len(KINDS)} fractions ({' / '.join(KINDS)}) >= 0 summing "
                       f"to 1 and random_reach > 0, got {self.mix}, {self.random_reach}")
    if self.image_size < 8 or self.episode_length < 2 or not self.noise_levels:
      raise ValueError(f"need image_size >= 8, episode_length >= 2 and noise levels, got "
                       f"{self.image_size}, {self.episode_length}, {self.noise_levels}")
    if min(self.noise_levels) < 0 or min(self.chunk, self.batch, self.action_repeat) < 1:
      raise ValueError(f"noise levels must be >= 0 and chunk, batch, action_repeat >= 1, got "
                       f"{self.noise_levels}, {self.chunk}, {self.batch}, {self.action_repeat}")

  def episode_noise(self, num_episodes: int) -> np.ndarray:
    """The policy noise of each of ``num_episodes`` episodes of a split ``[N]`` float32, as
    stored in ``observation/policy_noise``: the scripted pushes cycle through
    ``noise_levels`` (in the order of :func:`episode_kinds`), the random and idle agents are
    :data:`RANDOM_AGENT` / :data:`IDLE_AGENT`. Decided by the config alone."""
    kinds = episode_kinds(self.mix, num_episodes)
    scripted = np.cumsum(kinds == 0) - 1  # index of each scripted episode among the scripted
    levels = np.asarray(self.noise_levels, np.float32)[scripted % len(self.noise_levels)]
    return np.select([kinds == 0, kinds == 1], [levels, RANDOM_AGENT], IDLE_AGENT
                     ).astype(np.float32)

  def actions_for(self, control_steps: int) -> int:
    """Actions that take ``control_steps`` control steps of 0.1 s, each held for
    ``action_repeat`` of them (at least one action)."""
    return max(1, control_steps // self.action_repeat)

  @property
  def name(self) -> str:
    noise = "-".join(f"{n:g}" for n in self.noise_levels)
    return (f"s{self.image_size}_l{self.episode_length}_e{self.train_episodes}-"
            f"{self.test_episodes}_n{noise}_c{self.chunk}_o{self.max_offset:g}"
            f"_a{self.max_angle:g}_seed{self.seed}{self._variant_name()}")

  def _variant_name(self) -> str:
    """Empty for the defaults (all scripted, no action repeat), so that the datasets written
    before the mix and the repeat existed keep their names."""
    repeat = "" if self.action_repeat == 1 else f"_k{self.action_repeat}"
    if self.mix == (1.0, 0.0, 0.0):
      return repeat
    return "_m" + "-".join(f"{f:g}" for f in self.mix) + f"_r{self.random_reach:g}" + repeat


def _draws(config: PushTConfig, num_episodes: int, rng: np.random.Generator):
  """What ``rng`` (and the mix) decide of ``num_episodes`` episodes, ``config.batch`` at a time:
  per batch the episode kinds ``[b]`` (:func:`episode_kinds`), the noise levels ``[b]`` (cycling
  through ``config.noise_levels`` over the scripted episodes; :data:`RANDOM_AGENT` /
  :data:`IDLE_AGENT` for the others), the start states ``[b, 5]`` and the simulation's key seed.
  The kinds draw nothing from ``rng``: the start states are the same for every mix."""
  kinds = episode_kinds(config.mix, num_episodes)
  noise = config.episode_noise(num_episodes)
  for first in range(0, num_episodes, config.batch):
    count = min(config.batch, num_episodes - first)
    states = simulator.random_initial_states(rng, count, max_offset=config.max_offset,
                                             max_angle=config.max_angle)
    yield (kinds[first:first + count], noise[first:first + count], states,
           int(rng.integers(2**31)))


@dataclasses.dataclass(frozen=True)
class RandomAgent:
  """A random agent for the data: every call (a chunk) a waypoint, the T's centre seen in the
  newest frame plus an offset uniform in the disc of radius ``reach`` px, and as target the step
  of at most ``max_step`` px from the agent towards it (the scripted pusher's push step), repeated
  ``chunk`` times. The T is about 120 px across, so some waypoints lie in or beyond it (contact,
  from whichever side the agent comes) and some beside it (a T that stays where it is)."""

  chunk: int = 1
  reach: float = 160.0
  max_step: float = 60.0

  def __call__(self, frames, key: jax.Array) -> jax.Array:
    """``frames [B, c, H, W, 3]`` in [-1, 1] (the newest last) -> actions ``[B, chunk, 2]``."""
    block, agent, _ = simulator.centroids(jnp.asarray(frames)[:, -1])
    radius_key, angle_key = jax.random.split(key)
    radius = self.reach * jnp.sqrt(jax.random.uniform(radius_key, (block.shape[0], 1)))
    angle = jax.random.uniform(angle_key, (block.shape[0], 1), maxval=2 * jnp.pi)
    step = block + radius * jnp.concatenate([jnp.cos(angle), jnp.sin(angle)], -1) - agent
    length = jnp.linalg.norm(step, axis=-1, keepdims=True)
    target = agent + step * jnp.minimum(1.0, self.max_step / jnp.maximum(length, 1e-6))
    target = jnp.clip(target, 0.0, simulator.WORKSPACE)
    return jnp.repeat(target[:, None], self.chunk, axis=1)


def _policy(config: PushTConfig, kinds, noise, states):
  """The batch's policy ``(frames, key) -> [b, chunk, 2]``: per episode the scripted pusher at its
  noise level, the random agent or the idle agent (its start position as the target). All
  scripted (the default): the pusher alone, with the key as before the mix existed."""
  expert = simulator.PushPolicy(chunk=config.chunk)
  if (kinds == 0).all():
    return lambda frames, key: expert.act(frames, key, noise)
  random_agent = RandomAgent(chunk=config.chunk, reach=config.random_reach)
  scripted = np.where(kinds == 0, noise, 0.0)
  idle = jnp.repeat(jnp.asarray(states[:, None, :2], jnp.float32), config.chunk, axis=1)
  kind = jnp.asarray(kinds)[:, None, None]

  def policy(frames, key):
    push = expert.act(frames, key, scripted)
    wander = random_agent(frames, jax.random.fold_in(key, 1))
    return jnp.where(kind == 0, push, jnp.where(kind == 1, wander, idle))

  return policy


def collect(config: PushTConfig, num_episodes: int, rng: np.random.Generator, workers: int = 1):
  """Simulate ``num_episodes`` episodes, ``config.batch`` at a time, cycling through the noise
  levels (and the episode kinds of ``config.mix``); yields
  :class:`wmjax.data.synthetic.GeneratedEpisode`. ``workers > 1`` simulates the batches in that
  many processes (spawned, JAX on their CPU); the episodes are the same for any number."""
  if workers < 1:
    raise ValueError(f"workers must be >= 1, got {workers}")
  draws = list(_draws(config, num_episodes, rng))  # all of rng's draws, before any simulation
  if workers == 1 or len(draws) < 2:
    for draw in draws:
      yield from _simulate_batch(config, draw)
    return
  context = multiprocessing.get_context("spawn")  # a forked JAX runtime can deadlock
  with futures.ProcessPoolExecutor(min(workers, len(draws)), mp_context=context,
                                   initializer=_on_cpu) as pool:
    for batch in pool.map(_simulate_batch, itertools.repeat(config), draws):
      yield from batch


def _on_cpu() -> None:
  """A worker's JAX runs on the CPU: the policies are light, and the accelerator is the
  trainer's."""
  jax.config.update("jax_platforms", "cpu")


def _simulate_batch(config: PushTConfig, draw) -> list[synthetic.GeneratedEpisode]:
  """The episodes of one of :func:`_draws`' batches ``(kinds, noise, states, seed)``."""
  kinds, noise, states, seed = draw
  policy = _policy(config, kinds, noise, states)
  run = simulator.simulate_policy(policy, states, config.episode_length - 1,
                                  image_size=config.image_size, key=jax.random.key(seed),
                                  action_repeat=config.action_repeat)
  episodes = []
  for i in range(len(states)):
    actions = np.concatenate([run["actions"][i], run["state"][i, -1:, :2]])  # last: stay
    coverage = run["coverage"][i]
    episodes.append(synthetic.GeneratedEpisode(
        images=run["frames"][i], actions=actions.astype(np.float32), instruction=INSTRUCTION,
        rewards=np.clip(coverage / simulator.SUCCESS_COVERAGE, 0, 1).astype(np.float32),
        observations={"state": run["state"][i], "coverage": coverage,
                      "success": coverage > simulator.SUCCESS_COVERAGE,
                      "policy_noise": np.full(len(coverage), noise[i], np.float32)}))
  return episodes


class PushT(synthetic.SyntheticBuilder):
  """Push-T episodes from gym-pusht driven by a scripted pusher at several noise levels."""
  # (the docstring is the dataset's description in dataset_info.json: kept as it was written
  # before the mix of random and idle agents existed)

  name = "pusht"
  VERSION = tfds.core.Version("1.0.0")
  RELEASE_NOTES = {"1.0.0": "Scripted pushes near the goal with per-step coverage and state."}

  def action_dim(self) -> int:
    return 2

  def observation_features(self):
    scalar = tfds.features.Scalar(dtype=np.float32)
    return {"state": tfds.features.Tensor(shape=(5,), dtype=np.float32), "coverage": scalar,
            "success": np.bool_, "policy_noise": scalar}

  def __init__(self, *, workers: int = 1, **kwargs):
    self.workers = workers  # processes simulating at once (:func:`collect`)
    super().__init__(**kwargs)

  def episodes(self, count, rng):
    return collect(self.params, count, rng, self.workers)

  def metadata(self):
    """The parameters; the mix's and the action repeat's only where they are not the defaults,
    so that the datasets written before they existed are written to the byte as they were."""
    values = super().metadata()
    if values["mix"] == PushTConfig.mix:
      values = {k: v for k, v in values.items() if k not in ("mix", "random_reach")}
    if values["action_repeat"] == PushTConfig.action_repeat:
      values = {k: v for k, v in values.items() if k != "action_repeat"}
    return values

  @classmethod
  def check_can_write(cls):
    simulator.check_installed()

  @classmethod
  def start_states(cls, params, split):
    """``reset_to_state`` vectors ``[N, 5]`` every episode of ``split`` started from."""
    draws = _draws(params, cls.episode_count(params, split), synthetic.stream(params.seed, split))
    return np.concatenate([states for _, _, states, _ in draws])


def prepare(data_dir: str, config: PushTConfig = PushTConfig(), workers: int = 1) -> str:
  """Simulate and write the dataset under ``data_dir`` (once), in ``workers`` processes; returns
  the builder directory."""
  if workers < 1:  # before anything is written
    raise ValueError(f"workers must be >= 1, got {workers}")
  return synthetic.prepare(PushT, data_dir, config, workers=workers)
