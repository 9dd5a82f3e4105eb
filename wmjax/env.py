"""``WorldModelEnv``: a batched, gymnasium-style closed-loop environment over a world model.

Each :meth:`WorldModelEnv.step` takes an action chunk of up to ``horizon`` raw actions per
environment, normalises it with the checkpoint's action statistics, generates the frames that
follow with one jitted block (:func:`wmjax.rollout.sample_block`) and slides the context window.
Step ``k`` samples with ``block_key(rng, k)``, so a policy that sends the same chunks gets the
frames of the open-loop :func:`wmjax.rollout.rollout` with the same key. Frames go in and come
out as RGB (float32 in [-1, 1]; uint8 accepted): a latent model's codec encodes the initial frames
and decodes the generated ones, while the window stays in the model's space. Every frame of the
episode is kept for :meth:`video`.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding
from numpy.typing import ArrayLike

from wmjax.codecs import Codec, PixelCodec
from wmjax.data.stats import ActionStats
from wmjax.frames import to_model
from wmjax.model import LoadedModel, WorldModel
from wmjax.parallel import replicated_like, shard_rollout_batch
from wmjax.rollout import block_key, sample_block

RewardFn = Callable[[np.ndarray, str | list[str] | None], np.ndarray]


class WorldModelEnv:
  """``B`` environments stepped together in one world model.

  ``context``: frames kept in the window (``c``); ``horizon``: frames generated per step (``h``);
  ``c + h`` must fit the model's ``num_frames``. ``action_stats`` / ``normalization``: how raw
  actions are normalised (``None``: actions are already normalised). ``reward_fn(new_frames
  [B, k, H, W, C], instruction) -> [B]`` gives the step reward (0 without one). ``max_steps``:
  frames after which an episode is truncated. ``codec``: RGB <-> the model's space (default:
  pixels); ``frame_shape``: the RGB frames ``(H, W, C)`` reset must get, if checked.
  """

  def __init__(self, world_model: WorldModel, params: Any, *, context: int, horizon: int,
               action_stats: ActionStats | None = None, normalization: str = "mean_std",
               frame_shape: tuple[int, int, int] | None = None, seed: int | jax.Array = 0,
               reward_fn: RewardFn | None = None, max_steps: int | None = None,
               codec: Codec | None = None):
    num_frames = world_model.network.num_frames
    if context < 1 or horizon < 1 or context + horizon > num_frames:
      raise ValueError(f"need context >= 1, horizon >= 1 and context + horizon <= {num_frames} "
                       f"(model num_frames), got context={context}, horizon={horizon}")
    self.world_model, self.params = world_model, params
    self.context, self.horizon = context, horizon
    self.action_stats, self.normalization = action_stats, normalization
    self.frame_shape = None if frame_shape is None else tuple(frame_shape)
    self.rng = jax.random.key(seed) if isinstance(seed, int) else seed
    self.reward_fn, self.max_steps = reward_fn, max_steps
    self.codec = codec or PixelCodec()
    self.instruction: str | list[str] | None = None
    self._window = None

  @classmethod
  def from_model(cls, model: LoadedModel, *, context: int | None = None,
                 horizon: int | None = None, **kwargs) -> "WorldModelEnv":
    """An environment over a loaded checkpoint (:func:`wmjax.model.load_model`): its
    codec, action statistics and normalisation, and by default its rollout context / horizon."""
    config = model.config
    return cls(model.world_model, model.params, context=context or config.rollout.context,
               horizon=horizon or config.rollout.horizon, action_stats=model.action_stats,
               normalization=config.data.normalization, frame_shape=model.image_shape,
               codec=model.codec, **kwargs)

  @property
  def action_dim(self) -> int:
    return self.world_model.network.action_dim

  @property
  def num_envs(self) -> int:
    self._require_reset()
    return self._window.shape[0]

  def _require_reset(self) -> None:
    if self._window is None:
      raise RuntimeError("call reset(initial_frames) before step()")

  def _normalize(self, actions, name: str, length: tuple[int, int]) -> np.ndarray:
    actions = np.asarray(actions, np.float32)
    b = self._window.shape[0]
    if actions.ndim != 3 or actions.shape[0] != b or actions.shape[2] != self.action_dim or not (
        length[0] <= actions.shape[1] <= length[1]):
      raise ValueError(f"{name} must be [B={b}, k, A={self.action_dim}] with {length[0]} <= k <= "
                       f"{length[1]}, got shape {actions.shape}")
    if not np.isfinite(actions).all():
      raise ValueError(f"{name} contain NaN or inf values")
    if self.action_stats is None:
      return actions
    return self.action_stats.normalize(actions, self.normalization)

  def reset(self, initial_frames: ArrayLike, instruction: str | list[str] | None = None,
            context_actions: ArrayLike | None = None) -> tuple[jax.Array, dict]:
    """Start ``B`` episodes from ``initial_frames [B, c0, H, W, C]`` (``1 <= c0 <= context``;
    uint8 or [-1, 1]) with the raw actions between them, ``context_actions [B, c0-1, A]``, if
    known. Returns (the initial frames in [-1, 1], info)."""
    frames = jnp.asarray(to_model(initial_frames))
    if frames.ndim != 5 or not 1 <= frames.shape[1] <= self.context:
      raise ValueError(f"initial_frames must be [B, c0, H, W, C] with 1 <= c0 <= "
                       f"{self.context}, got shape {tuple(frames.shape)}")
    if self.frame_shape is not None and tuple(frames.shape[2:]) != self.frame_shape:
      raise ValueError(f"frames must be {self.frame_shape} (H, W, C) for this model, got "
                       f"{tuple(frames.shape[2:])}")
    if not bool(jnp.isfinite(frames).all()):
      raise ValueError("initial_frames contain NaN or inf values")
    b, c0 = frames.shape[:2]
    # Episodes are split over the local devices (when B divides evenly); every step follows.
    window, = shard_rollout_batch(self.codec.encode(frames, jax.random.split(self.rng)[1]))
    self._window = jax.device_put(window, self._layout(window))
    self._history = np.zeros((b, c0 - 1, self.action_dim), np.float32)
    self._known = np.zeros((b, c0 - 1), bool)
    if context_actions is not None:
      self._history = self._normalize(context_actions, "context_actions", (c0 - 1, c0 - 1))
      self._known[:] = True
    self.instruction = instruction
    self._frames = [np.asarray(frames)]
    self._step = 0
    return frames, {"frames": c0}

  def _layout(self, window: jax.Array) -> jax.sharding.Sharding:
    """Where the window lives from reset on, every step's new window put back there, so that all
    steps run the program the first one compiled (a jitted step returns its output committed,
    which an uncommitted first window is not): split over the rollout mesh when the batch
    divides, else beside the parameters (replicated on their mesh, or on their device)."""
    if isinstance(window.sharding, NamedSharding):
      return window.sharding
    return replicated_like(self.params) or window.sharding

  def step(self, action_chunk: ArrayLike) -> tuple[jax.Array, np.ndarray, np.ndarray, np.ndarray, dict]:
    """Apply ``action_chunk [B, k, A]`` (raw, ``1 <= k <= horizon``): returns (the ``k`` new
    frames ``[B, k, H, W, C]``, reward ``[B]``, terminated ``[B]``, truncated ``[B]``, info)."""
    self._require_reset()
    actions = self._normalize(action_chunk, "action_chunk", (1, self.horizon))
    b, k = actions.shape[:2]
    pad = self.horizon - k
    window_actions = np.concatenate(
        [self._history, actions, np.zeros((b, pad, self.action_dim), np.float32)], axis=1)
    window_mask = np.concatenate([self._known, np.ones((b, k), bool), np.zeros((b, pad), bool)], 1)
    new = sample_block(self.world_model, self.params, self._window, jnp.asarray(window_actions),
                       block_key(self.rng, self._step), jnp.asarray(window_mask))[:, :k]
    frames = self.codec.decode(new)
    actions_so_far = np.concatenate([self._history, actions], axis=1)
    known_so_far = np.concatenate([self._known, np.ones((b, k), bool)], axis=1)
    # laid out as reset laid it out, so that every step runs the program the first one compiled
    self._window = jax.device_put(jnp.concatenate([self._window, new], axis=1)[:, -self.context:],
                                  self._window.sharding)
    between = self._window.shape[1] - 1  # actions between the window's frames
    self._history = actions_so_far[:, actions_so_far.shape[1] - between:]
    self._known = known_so_far[:, known_so_far.shape[1] - between:]
    self._frames.append(np.asarray(frames))
    self._step += 1
    total = sum(f.shape[1] for f in self._frames)
    reward = (np.zeros(b, np.float32) if self.reward_fn is None
              else np.asarray(self.reward_fn(np.asarray(frames), self.instruction), np.float32))
    truncated = np.full(b, self.max_steps is not None and total >= self.max_steps)
    return frames, reward, np.zeros(b, bool), truncated, {"frames": total, "step": self._step}

  def video(self) -> np.ndarray:
    """Every frame of the current episodes, initial frames included: ``[B, T, H, W, C]``."""
    self._require_reset()
    return np.concatenate(self._frames, axis=1)
