"""The WPE gridworld (appendix C.1) as a real RLDS TFDS dataset in ArrayRecord.

``n`` coloured squares on a black frame, each with a random initial position; at every step each
square gets its own 2-D velocity, uniform in ``[-max_speed, max_speed]`` pixels, which is added to
its position (clipped so the square stays inside the frame). With ``snap_to_pixels`` (the default)
every position is rounded to the pixel grid the frame is drawn on, so a frame shows the whole
state and the next frame follows from it and the action; without it the state keeps a sub-pixel
part that no frame shows (the frame rounds it), and the same frame and action can lead to two
different next frames. The action is the concatenation of
the ``n`` velocities ``[vy_0, vx_0, vy_1, vx_1, ...]``; square ``i`` always has colour ``i``, so
every action slot maps to one square. Each step stores the true square centres
(``observation/square_positions [n, 2]``, (y, x) pixels) so action-following can be scored
exactly. Step ``t``'s action moves frame ``t`` to ``t+1``; the last step's action is zero.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import tensorflow_datasets as tfds

from wmjax.data import oxe, synthetic

# Fixed colour per action slot (RGB); more squares than colours is an error.
COLORS = np.array([(255, 64, 64), (64, 255, 64), (64, 128, 255), (255, 255, 64), (255, 64, 255),
                   (64, 255, 255), (255, 160, 32), (160, 96, 255)], np.uint8)

oxe.register(oxe.DatasetSpec("gridworld", "wmjax",
                             extra_keys=("observation/square_positions",)))


@dataclasses.dataclass(frozen=True)
class GridworldConfig:
  """Defaults fit CPU training: 16x16 frames, 2 squares of 4 px, speeds up to 2 px / step,
  positions on the pixel grid."""

  num_squares: int = 2
  image_size: int = 16
  square_size: int = 4
  max_speed: float = 2.0
  episode_length: int = 32
  train_episodes: int = 512
  test_episodes: int = 32
  seed: int = 0
  snap_to_pixels: bool = True

  @classmethod
  def from_dict(cls, values) -> "GridworldConfig":
    """From a config section; a key left out takes its default here."""
    return cls(**dict(values))

  @classmethod
  def from_saved(cls, values) -> "GridworldConfig":
    """From the section of a saved config (a workdir's ``config.json``): one written before
    ``snap_to_pixels`` existed described sub-pixel positions, so there a missing key means False
    (the dataset its model was trained on)."""
    return cls(**{"snap_to_pixels": False, **dict(values)})

  def __post_init__(self):
    if not 1 <= self.num_squares <= len(COLORS):
      raise ValueError(f"num_squares must be in [1, {len(COLORS)}], got {self.num_squares}")
    if not 0 < self.square_size < self.image_size:
      raise ValueError(f"square_size must be in (0, image_size={self.image_size}), got "
                       f"{self.square_size}")
    if self.episode_length < 2:
      raise ValueError(f"episode_length must be >= 2, got {self.episode_length}")

  @property
  def name(self) -> str:
    return (f"n{self.num_squares}_s{self.image_size}_q{self.square_size}_v{self.max_speed:g}"
            f"_l{self.episode_length}_e{self.train_episodes}-{self.test_episodes}_seed{self.seed}"
            + ("_px" if self.snap_to_pixels else ""))


def first_centres(config: GridworldConfig, rng: np.random.Generator, count: int) -> np.ndarray:
  """``count`` start states ``[count, n, 2]``, drawn as an episode's first frame is: uniform
  inside the frame, snapped to the pixel grid when the config snaps."""
  half = config.square_size / 2
  centres = rng.uniform(half, config.image_size - half, (count, config.num_squares, 2))
  if config.snap_to_pixels:
    centres = np.round(centres - half) + half
  return centres.astype(np.float32)


def simulate(config: GridworldConfig, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
  """One episode: square centres ``[L, n, 2]`` and actions ``[L, 2n]`` (last action zero)."""
  n, length, half = config.num_squares, config.episode_length, config.square_size / 2
  low, high = half, config.image_size - half
  # the centre of a square drawn from whole pixel ``k`` on is ``k + half``
  snap = (lambda c: np.round(c - half) + half) if config.snap_to_pixels else (lambda c: c)
  centres = np.empty((length, n, 2), np.float32)
  centres[0] = first_centres(config, rng, 1)[0]
  velocities = rng.uniform(-config.max_speed, config.max_speed, (length, n, 2)).astype(np.float32)
  velocities[-1] = 0.0
  for t in range(1, length):
    centres[t] = np.clip(snap(centres[t - 1] + velocities[t - 1]), low, high)
  return centres, velocities.reshape(length, 2 * n)


def render(centres: np.ndarray, config: GridworldConfig) -> np.ndarray:
  """Square centres ``[n, 2]`` -> uint8 frame ``[S, S, 3]``; later squares are drawn on top."""
  frame = np.zeros((config.image_size, config.image_size, 3), np.uint8)
  for i, (cy, cx) in enumerate(centres):
    top = int(round(cy - config.square_size / 2))
    left = int(round(cx - config.square_size / 2))
    frame[top:top + config.square_size, left:left + config.square_size] = COLORS[i]
  return frame


class Gridworld(synthetic.SyntheticBuilder):
  """The WPE gridworld (appendix C.1) with true square positions; one config per
  :class:`GridworldConfig`."""

  VERSION = tfds.core.Version("1.0.0")
  RELEASE_NOTES = {"1.0.0": "WPE appendix C.1 gridworld with true square positions."}

  def action_dim(self) -> int:
    return 2 * self.params.num_squares

  def observation_features(self):
    return {"square_positions": tfds.features.Tensor(shape=(self.params.num_squares, 2),
                                                     dtype=np.float32)}

  def episodes(self, count, rng):
    g = self.params
    for _ in range(count):
      centres, actions = simulate(g, rng)
      yield synthetic.GeneratedEpisode(
          images=np.stack([render(c, g) for c in centres]), actions=actions,
          instruction="move the squares", rewards=np.zeros(g.episode_length, np.float32),
          observations={"square_positions": centres})

  @classmethod
  def start_states(cls, params, split):
    """Square centres ``[N, n, 2]`` of every episode's first frame in ``split``."""
    rng = synthetic.stream(params.seed, split)
    count = cls.episode_count(params, split)
    return np.stack([simulate(params, rng)[0][0] for _ in range(count)]).astype(np.float64)


def prepare(data_dir: str, config: GridworldConfig = GridworldConfig()) -> str:
  """Write the dataset as ArrayRecord under ``data_dir`` (once); returns the builder directory."""
  return synthetic.prepare(Gridworld, data_dir, config)
