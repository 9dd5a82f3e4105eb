"""MetaWorld episodes seen by several cameras, as an RLDS TFDS dataset in ArrayRecord.

Every episode starts from a start state of its split's own random stream
(:func:`.simulator.random_start_states`: the hand's initial position and the task's object / goal
placement; :meth:`MetaWorld.start_states` replays them without simulating) and is driven by one
of three kinds of agent, interleaved by a deterministic weighted round robin over ``mix``
(:func:`wmjax.data.synthetic.episode_kinds`): MetaWorld's scripted expert with Gaussian action
noise cycling through ``noise_levels``, a random agent (a new random move every two actions: the
arm reaches every side of the objects) and an idle agent (a still scene: nothing moves when
untouched). Each action is held ``action_repeat`` control steps and one frame is kept per
action.

A step stores the first camera of ``views`` as ``observation/image`` and the others as
``observation/image_1``, ``image_2``, ... (all ``image_size`` square), and beside them
``observation/state`` (hand and object positions, metres, :data:`.simulator.STATE_SIZE`),
``observation/ee_px`` (the hand's ``(col, row)`` pixel in the first view), ``observation/success``
(MetaWorld's success signal), ``observation/policy_noise`` (the expert's noise level;
:data:`RANDOM_AGENT` / :data:`IDLE_AGENT` for the others), ``observation/start_state`` and
``observation/sim_state`` (MuJoCo's ``qpos``, ``qvel`` and hand target: an exact replay,
:meth:`.simulator.ArmSimulator.restore`). The action is MetaWorld's ``[dx, dy, dz, grip]``
(step ``t``'s leads to frame ``t + 1``; the last step's is idle). The reward is the success.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import multiprocessing
import multiprocessing.util
import sys
from concurrent import futures

import numpy as np
import tensorflow_datasets as tfds

from wmjax.data import oxe, synthetic
from wmjax.tasks.metaworld import simulator

KINDS = ("expert", "random", "idle")  # the episode kinds of ``MetaWorldConfig.mix``, in its order
RANDOM_AGENT, IDLE_AGENT = -1.0, -2.0  # ``observation/policy_noise`` of the other kinds
DEFAULT_VIEWS = ("topview", "gripperPOV")
EXTRAS = ("observation/state", "observation/ee_px", "observation/success",
          "observation/policy_noise", "observation/start_state")


def camera_keys(count: int) -> tuple[str, ...]:
  """The step keys of ``count`` views: ``observation/image``, ``observation/image_1``, ..."""
  return ("observation/image",) + tuple(f"observation/image_{i}" for i in range(1, count))


# the spec of the default two views (a dataset of another number of views lists its camera_keys
# in config.data.spec.image_keys); several image keys are tiled left to right into one frame
oxe.register(oxe.DatasetSpec("metaworld", "wmjax", image_keys=camera_keys(len(DEFAULT_VIEWS)),
                             extra_keys=EXTRAS))


@dataclasses.dataclass(frozen=True)
class MetaWorldConfig:
  """Defaults fit CPU training: two 48x48 cameras, 22 frames of 5 control steps an episode."""

  task: str = "button-press-v3"
  views: tuple[str, ...] = DEFAULT_VIEWS
  image_size: int = 48
  episode_length: int = 22
  action_repeat: int = 5
  train_episodes: int = 400
  test_episodes: int = 40
  noise_levels: tuple[float, ...] = (0.0, 0.2, 0.4, 0.6)
  mix: tuple[float, ...] = (0.6, 0.2, 0.2)  # fractions of expert / random / idle agents
  seed: int = 0

  @classmethod
  def from_dict(cls, values) -> "MetaWorldConfig":
    """From a config section."""
    return cls(**dict(values))

  def __post_init__(self):
    simulator.check_task(self.task)
    views = self.views.split(",") if isinstance(self.views, str) else self.views
    object.__setattr__(self, "views", simulator.check_views(v.strip() for v in views))
    object.__setattr__(self, "noise_levels", tuple(float(n) for n in self.noise_levels))
    object.__setattr__(self, "mix", tuple(float(f) for f in self.mix))
    if len(self.mix) != len(KINDS) or min(self.mix) < 0 or abs(sum(self.mix) - 1) > 1e-6:
      raise ValueError(f"mix must be {len(KINDS)} fractions ({' / '.join(KINDS)}) >= 0 summing "
                       f"to 1, got {self.mix}")
    if self.image_size < 8 or self.episode_length < 2 or not self.noise_levels:
      raise ValueError(f"need image_size >= 8, episode_length >= 2 and noise levels, got "
                       f"{self.image_size}, {self.episode_length}, {self.noise_levels}")
    if min(self.noise_levels) < 0 or self.action_repeat < 1:
      raise ValueError(f"noise levels must be >= 0 and action_repeat >= 1, got "
                       f"{self.noise_levels}, {self.action_repeat}")

  def episode_noise(self, num_episodes: int) -> np.ndarray:
    """Each episode's ``observation/policy_noise`` ``[N]``: the experts cycle through
    ``noise_levels``, the others are :data:`RANDOM_AGENT` / :data:`IDLE_AGENT`."""
    kinds = synthetic.episode_kinds(self.mix, num_episodes)
    expert = np.cumsum(kinds == 0) - 1
    levels = np.asarray(self.noise_levels, np.float32)[expert % len(self.noise_levels)]
    return np.select([kinds == 0, kinds == 1], [levels, RANDOM_AGENT], IDLE_AGENT
                     ).astype(np.float32)

  @property
  def name(self) -> str:
    noise = "-".join(f"{n:g}" for n in self.noise_levels)
    mix = "-".join(f"{f:g}" for f in self.mix)
    return (f"{self.task}_{'-'.join(self.views)}_s{self.image_size}_l{self.episode_length}"
            f"_k{self.action_repeat}_e{self.train_episodes}-{self.test_episodes}_n{noise}"
            f"_m{mix}_seed{self.seed}")


def policy_for(task: str, noise: float):
  """The agent an episode of ``noise`` (its ``policy_noise``) was collected with."""
  if noise == RANDOM_AGENT:
    return simulator.RandomAgent()
  if noise == IDLE_AGENT:
    return simulator.idle
  return simulator.Expert(task, float(noise))


def _draws(params: MetaWorldConfig, num_episodes: int, rng: np.random.Generator):
  """``(start_states [N, D], policy noise [N], seeds [N])``: all of ``rng``'s draws for a split,
  the start states first (so :meth:`MetaWorld.start_states` replays them alone)."""
  states = simulator.random_start_states(simulator.StartSpace.of(params.task), rng, num_episodes)
  return states, params.episode_noise(num_episodes), rng.integers(2**31, size=num_episodes)


def run_episode(sim: simulator.ArmSimulator, act, start_state, steps: int,
                rng: np.random.Generator) -> dict[str, np.ndarray]:
  """``act(t, state [6], views [V, S, S, 3], rng) -> action [4]`` from ``start_state`` for
  ``steps`` actions (``state``: the simulator's true one):
  ``{'frames' [steps+1, V, S, S, 3], 'actions' [steps, 4], 'state' [steps+1, 6], 'ee_px'
  [steps+1, 2], 'success' [steps+1], 'sim_state' [steps+1, n]}``."""
  sim.reset(start_state)
  out = {k: [] for k in ("frames", "actions", "state", "ee_px", "success", "sim_state")}
  success = False
  for t in range(steps + 1):
    out["frames"].append(sim.render())
    out["state"].append(sim.state())
    out["ee_px"].append(sim.pixel(sim.env.tcp_center, sim.views[0]))
    out["success"].append(success)
    out["sim_state"].append(sim.sim_state())
    if t < steps:
      action = act(t, out["state"][-1], out["frames"][-1], rng)
      out["actions"].append(action)
      _, success = sim.step(action)
  return {k: np.stack(v) for k, v in out.items()}


def _new_simulator(params: MetaWorldConfig) -> simulator.ArmSimulator:
  return simulator.ArmSimulator(params.task, params.views, params.image_size, params.action_repeat)


_worker_simulator: simulator.ArmSimulator | None = None  # a pool worker's, for every split


def _start_worker(params: MetaWorldConfig) -> None:
  """A pool worker's initialiser: its simulator, started once and closed when the worker ends."""
  global _worker_simulator
  _worker_simulator = _new_simulator(params)
  multiprocessing.util.Finalize(None, _worker_simulator.close, exitpriority=10)


def _simulate_in_worker(params: MetaWorldConfig, draws) -> list[synthetic.GeneratedEpisode]:
  return _episodes_in(_worker_simulator, params, draws)


def _episodes_in(sim: simulator.ArmSimulator, params: MetaWorldConfig, draws
                 ) -> list[synthetic.GeneratedEpisode]:
  episodes = []
  for start, noise, seed in draws:
    policy = policy_for(params.task, noise)
    run = run_episode(sim, lambda t, state, views, rng: policy(state, rng), start,
                      params.episode_length - 1, np.random.default_rng(seed))
    length = params.episode_length
    actions = np.concatenate([run["actions"], simulator.idle(None, None)[None]])
    frames = run["frames"]
    episodes.append(synthetic.GeneratedEpisode(
        images=frames[:, 0], actions=actions.astype(np.float32),
        instruction=f"{params.task.removesuffix('-v3').replace('-', ' ')}",
        rewards=run["success"].astype(np.float32),
        cameras={key.split("/")[-1]: frames[:, v]
                 for v, key in enumerate(camera_keys(len(params.views))) if v},
        observations={"state": run["state"], "ee_px": run["ee_px"],
                      "success": run["success"],
                      "policy_noise": np.full(length, noise, np.float32),
                      "start_state": np.repeat(start[None].astype(np.float32), length, 0),
                      "sim_state": run["sim_state"]}))
  return episodes


@functools.lru_cache(maxsize=None)
def sim_state_size(task: str) -> int:
  """Numbers in one ``observation/sim_state`` of ``task``."""
  env = simulator._make_env(task)
  return env.model.nq + env.model.nv + env.data.mocap_pos.size + env.data.mocap_quat.size


class MetaWorld(synthetic.SyntheticBuilder):
  """MetaWorld (Sawyer arm) episodes from several cameras: a noisy scripted expert, random and
  idle agents."""

  name = "metaworld"
  VERSION = tfds.core.Version("1.0.0")
  RELEASE_NOTES = {"1.0.0": "Two cameras, expert / random / idle agents, states for replay."}

  def __init__(self, *, workers: int = 1, **kwargs):
    self.workers = workers
    # the splits share one simulator: in this process, or one in each of the pool's processes
    self._simulator = self._pool = None
    super().__init__(**kwargs)

  def _download_and_prepare(self, dl_manager, download_config):
    try:
      return super()._download_and_prepare(dl_manager, download_config)
    finally:
      if self._simulator is not None:
        self._simulator.close()
        self._simulator = None
      if self._pool is not None:
        self._pool.shutdown()
        self._pool = None

  def action_dim(self) -> int:
    return simulator.ACTION_DIM

  def camera_features(self):
    return tuple(key.split("/")[-1] for key in camera_keys(len(self.params.views))[1:])

  def observation_features(self):
    vector = lambda n: tfds.features.Tensor(shape=(n,), dtype=np.float32)
    start = len(simulator.StartSpace.of(self.params.task).low)
    return {"state": vector(simulator.STATE_SIZE), "ee_px": vector(2), "success": np.bool_,
            "policy_noise": tfds.features.Scalar(dtype=np.float32), "start_state": vector(start),
            "sim_state": tfds.features.Tensor(shape=(sim_state_size(self.params.task),),
                                              dtype=np.float64)}

  def episodes(self, count, rng):
    states, noise, seeds = _draws(self.params, count, rng)
    draws = list(zip(states, noise, seeds))
    # in this process unless TensorFlow is loaded here (MuJoCo's EGL crashes beside it)
    if self.workers == 1 and "tensorflow" not in sys.modules:
      if self._simulator is None:
        self._simulator = _new_simulator(self.params)
      yield from _episodes_in(self._simulator, self.params, draws)
      return
    if self._pool is None:  # every worker one simulator, started once for all the splits
      self._pool = futures.ProcessPoolExecutor(
          self.workers, mp_context=multiprocessing.get_context("spawn"),
          initializer=_start_worker, initargs=(self.params,))
    workers = max(1, min(self.workers, count))
    chunks = [draws[i::workers] for i in range(workers)]
    done = list(self._pool.map(_simulate_in_worker, itertools.repeat(self.params), chunks))
    for index in range(count):  # back in the order of the draws
      yield done[index % workers][index // workers]

  @classmethod
  def check_can_write(cls):
    simulator.check_installed()

  @classmethod
  def start_states(cls, params, split):
    """``[N, D]`` start states of every episode of ``split``."""
    count = cls.episode_count(params, split)
    return _draws(params, count, synthetic.stream(params.seed, split))[0]


def prepare(data_dir: str, config: MetaWorldConfig = MetaWorldConfig(), workers: int = 1) -> str:
  """Simulate and write the dataset under ``data_dir`` (once), in ``workers`` processes; returns
  the builder directory."""
  if workers < 1:
    raise ValueError(f"workers must be >= 1, got {workers}")
  return synthetic.prepare(MetaWorld, data_dir, config, workers=workers)
