"""Push-T (gym-pusht): the ground-truth simulator, its frame geometry and scripted policies.

World coordinates are gym-pusht's: ``(x, y)`` in ``[0, 512]^2``, ``y`` pointing down the image,
so pixel ``(row, col)`` of an ``S x S`` render covers world ``y, x`` in ``[row, row + 1) * 512 / S``.
The action is the agent's target position ``(x, y)``; the block is a T (a 120 x 30 bar on a 30 x 90
stem) and the goal is the T at pose ``(256, 256, pi / 4)``. Coverage is the goal's area covered
by the block, success is coverage > 0.95.

Everything a policy or a reward needs is read from rendered RGB frames (``[-1, 1]``), not from
the simulator's state, so the same functions run on simulator renders and on a world model's
imagined frames, in numpy or inside a jitted scan:

* :func:`classify_pixels` / :func:`object_masks`: nearest palette colour per pixel;
* :func:`centroids`: world position of the block and the agent;
* :func:`goal_mask` / :func:`frame_coverage`: goal-region pixels and the fraction the block covers;
* :class:`PushPolicy`: a frame-based controller that walks around the block and pushes its centre
  towards the goal's, with Gaussian action noise (``noise`` in units of the 512-px workspace, as
  WPE's 0.1 / 0.2 / 0.5 levels); a pure function ``(frames, key) -> action chunk``;
  :class:`StayPolicy` (do nothing) and :func:`policy_from_spec` (``push:0.2``, ``stay``,
  ``module:attribute``) for the command line.

:class:`PushTSimulator` steps ``B`` gym-pusht environments together and
:func:`simulate_policy` runs a policy in it closed loop, for ground-truth values.
"""

from __future__ import annotations

import dataclasses
import importlib
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from wmjax.frames import to_model
from wmjax.policy import load_policy

WORKSPACE = 512.0
GOAL_POSE = (256.0, 256.0, np.pi / 4)  # x, y, theta
SUCCESS_COVERAGE = 0.95
# pygame colour names gym-pusht draws with, in the order of PALETTE's classes.
PALETTE_NAMES = ("background", "goal", "block", "agent", "wall")
PALETTE = np.array([(255, 255, 255), (144, 238, 144), (119, 136, 153), (65, 105, 225),
                    (211, 211, 211)], np.float32)
BLOCK, AGENT, GOAL = PALETTE_NAMES.index("block"), PALETTE_NAMES.index("agent"), 1
# The T in its body frame: (x0, x1, y0, y1) of the bar and the stem.
T_RECTS = ((-60.0, 60.0, 0.0, 30.0), (-15.0, 15.0, 30.0, 120.0))
# Block centre of area in its body frame (bar 3600 px^2 at y=15, stem 2700 px^2 at y=75).
T_CENTROID = (0.0, (3600 * 15 + 2700 * 75) / 6300)

BLOCK_COG = (0.0, 45.0)  # gym-pusht's centre of gravity of the T, body frame

PolicyFn = Callable[[jax.Array, jax.Array], jax.Array]


def body_to_world(points, pose) -> np.ndarray:
  """Body-frame points ``[..., 2]`` of a pose ``(x, y, theta)`` -> world ``(x, y)``."""
  x, y, theta = pose
  c, s = np.cos(theta), np.sin(theta)
  points = np.asarray(points, np.float64)
  return np.stack([x + c * points[..., 0] - s * points[..., 1],
                   y + s * points[..., 0] + c * points[..., 1]], -1)


def goal_centroid() -> np.ndarray:
  """World ``(x, y)`` of the goal T's centre of area."""
  return body_to_world(np.array(T_CENTROID), GOAL_POSE)


def goal_mask(size: int, pose=GOAL_POSE) -> np.ndarray:
  """``[size, size]`` bool: pixels whose centre lies inside the T at ``pose``."""
  centres = (np.arange(size) + 0.5) * WORKSPACE / size
  ys, xs = np.meshgrid(centres, centres, indexing="ij")
  x, y, theta = pose
  c, s = np.cos(theta), np.sin(theta)
  local_x = c * (xs - x) + s * (ys - y)
  local_y = -s * (xs - x) + c * (ys - y)
  inside = np.zeros((size, size), bool)
  for x0, x1, y0, y1 in T_RECTS:
    inside |= (local_x >= x0) & (local_x <= x1) & (local_y >= y0) & (local_y <= y1)
  return inside


def classify_pixels(frames) -> jax.Array:
  """Index of the nearest palette colour: ``frames [..., H, W, 3]`` in [-1, 1] -> ``[..., H, W]``
  int32 (classes in :data:`PALETTE_NAMES` order)."""
  pixels = (jnp.asarray(frames, jnp.float32) + 1.0) * 127.5
  distance = jnp.sum((pixels[..., None, :] - jnp.asarray(PALETTE)) ** 2, axis=-1)
  return jnp.argmin(distance, axis=-1).astype(jnp.int32)


def object_masks(frames) -> tuple[jax.Array, jax.Array]:
  """Block and agent pixels, each ``[..., H, W]`` bool."""
  classes = classify_pixels(frames)
  return classes == BLOCK, classes == AGENT


def world_centroid(mask) -> tuple[jax.Array, jax.Array]:
  """World ``(x, y)`` centroid ``[..., 2]`` of an object's pixels ``mask [..., H, W]`` and whether
  it was seen ``[...]``; an unseen object's centroid is the frame centre."""
  h, w = mask.shape[-2:]
  ys = (jnp.arange(h) + 0.5) * WORKSPACE / h
  xs = (jnp.arange(w) + 0.5) * WORKSPACE / w
  count = mask.sum((-2, -1))
  cx = (mask * xs).sum((-2, -1)) / jnp.maximum(count, 1)
  cy = (mask * ys[:, None]).sum((-2, -1)) / jnp.maximum(count, 1)
  centre = jnp.stack([cx, cy], -1)
  return jnp.where((count > 0)[..., None], centre, WORKSPACE / 2), count > 0


def centroids(frames) -> tuple[jax.Array, jax.Array, jax.Array]:
  """World ``(x, y)`` centroids of the block and the agent (``[..., 2]`` each) and whether both
  were seen (``[...]``); an unseen object's centroid is the frame centre."""
  block, agent = object_masks(frames)
  block_xy, block_seen = world_centroid(block)
  agent_xy, agent_seen = world_centroid(agent)
  return block_xy, agent_xy, block_seen & agent_seen


def frame_coverage(frames) -> jax.Array:
  """Push-T coverage estimated from frames ``[..., H, W, 3]``: the fraction of the goal's pixels
  that show the block (the agent occluding the block counts as block) -> ``[...]``."""
  frames = jnp.asarray(frames)
  size = frames.shape[-3]
  if frames.shape[-2] != size:
    raise ValueError(f"Push-T frames must be square, got {frames.shape[-3:]}")
  goal = jnp.asarray(goal_mask(size))
  classes = classify_pixels(frames)
  covered = ((classes == BLOCK) | (classes == AGENT)) & goal
  return covered.sum((-2, -1)) / goal.sum()


@dataclasses.dataclass(frozen=True)
class PushPolicy:
  """Frame-based Push-T controller with Gaussian action noise.

  From the newest frame it finds the block and the agent. If the agent is behind the block
  (seen from the goal) it pushes through the block's centre towards the goal's; otherwise it
  walks to the push point ``standoff`` px behind the block, around the block's side when it is
  in front, aiming ``lead`` times as far as the waypoint (at most ``max_lead`` px) since the PD
  controller covers only part of the way per step. It stops within ``tolerance`` px. ``noise``:
  action noise standard deviation in units of the 512-px workspace.
  ``chunk``: actions per call (the same target, re-noised per step).
  """

  noise: float = 0.0
  chunk: int = 1
  standoff: float = 95.0
  push_step: float = 60.0
  tolerance: float = 8.0
  lead: float = 2.0
  max_lead: float = 120.0

  def target(self, frame) -> jax.Array:
    """Noise-free target ``(x, y)`` from frames ``[B, H, W, 3]`` -> ``[B, 2]``."""
    block, agent, _ = centroids(frame)
    goal = jnp.asarray(goal_centroid(), jnp.float32)
    offset = goal - block
    distance = jnp.linalg.norm(offset, axis=-1, keepdims=True)
    u = offset / jnp.maximum(distance, 1e-6)
    normal = jnp.stack([-u[..., 1], u[..., 0]], -1)
    rel = agent - block
    along = jnp.sum(rel * u, -1, keepdims=True)
    across = jnp.sum(rel * normal, -1, keepdims=True)
    push_point = block - u * self.standoff
    behind = (along < -0.6 * self.standoff) & (jnp.abs(across) < 30.0)
    side = jnp.where(across >= 0, 1.0, -1.0)
    around = block + normal * side * (self.standoff + 20.0) - u * 0.8 * self.standoff
    in_front = along > -0.5 * self.standoff
    waypoint = jnp.where(in_front, around, push_point)
    # PD control covers about a quarter of the way per step: aim past the waypoint
    lead = self.lead * (waypoint - agent)
    lead_length = jnp.linalg.norm(lead, axis=-1, keepdims=True)
    approach = agent + lead * jnp.minimum(1.0, self.max_lead / jnp.maximum(lead_length, 1e-6))
    push = agent + u * jnp.minimum(distance, self.push_step)
    target = jnp.where(behind, push, approach)
    done = distance < self.tolerance
    return jnp.clip(jnp.where(done, agent, target), 0.0, WORKSPACE)

  def __call__(self, frames, key: jax.Array) -> jax.Array:
    """``frames [B, c, H, W, 3]`` in [-1, 1] (the newest last) -> actions ``[B, chunk, 2]``."""
    return self.act(frames, key, self.noise)

  def act(self, frames, key: jax.Array, noise) -> jax.Array:
    """As calling the policy, with ``noise`` a scalar or one level per environment ``[B]``."""
    target = self.target(jnp.asarray(frames)[:, -1])
    scale = jnp.reshape(jnp.asarray(noise, jnp.float32), (-1, 1, 1)) * WORKSPACE
    jitter = scale * jax.random.normal(key, (target.shape[0], self.chunk, 2))
    return jnp.clip(target[:, None] + jitter, 0.0, WORKSPACE)


def random_initial_states(rng: np.random.Generator, n: int, *, max_offset: float = 90.0,
                          max_angle: float = 0.5, min_agent_distance: float = 110.0
                          ) -> np.ndarray:
  """``n`` states ``[agent_x, agent_y, block_x, block_y, block_angle]``: the block's centre
  ``<= max_offset`` px from the goal's and its angle within ``max_angle`` rad of the goal's, the
  agent anywhere ``>= min_agent_distance`` px from the block's centre."""
  states = np.empty((n, 5))
  goal_c = goal_centroid()
  for i in range(n):
    radius = max_offset * np.sqrt(rng.uniform())
    direction = rng.uniform(0, 2 * np.pi)
    angle = GOAL_POSE[2] + rng.uniform(-max_angle, max_angle)
    centre = goal_c + radius * np.array([np.cos(direction), np.sin(direction)])
    origin = centre - body_to_world(np.array(T_CENTROID), (0.0, 0.0, angle))
    while True:
      agent = rng.uniform(40, WORKSPACE - 40, 2)
      if np.linalg.norm(agent - centre) >= min_agent_distance:
        break
    states[i] = reset_state(agent, origin, angle)
  return states


def reset_state(agent, origin, angle: float) -> np.ndarray:
  """The ``reset_to_state`` vector that puts the block's body origin at ``origin`` with ``angle``.

  gym-pusht sets the block's position and then its angle, and pymunk rotates about the centre of
  gravity (body point ``(0, 45)``), so the position to pass is the centre of gravity's world
  position minus ``(0, 45)``."""
  cog = body_to_world(np.array(BLOCK_COG), (*origin, angle))
  return np.array([*agent, cog[0] - BLOCK_COG[0], cog[1] - BLOCK_COG[1], angle])


def check_installed() -> None:
  """ImportError naming the extra to install when gym-pusht is missing."""
  try:
    import gymnasium  # noqa: F401
    import gym_pusht  # noqa: F401  (registers gym_pusht/PushT-v0)
  except ImportError as e:
    raise ImportError(f"the Push-T simulator needs gym-pusht: pip install 'wmjax[pusht]' ({e})"
                      ) from e


class PushTSimulator:
  """``B`` gym-pusht environments stepped together, rendering ``image_size`` square frames.

  ``action_repeat = k``: one step holds its target for k control steps of 0.1 s (gym-pusht's
  own), and only the last one's frame is returned: one frame per decision, k times the motion
  per frame."""

  def __init__(self, num_envs: int, image_size: int = 96, action_repeat: int = 1):
    check_installed()
    import gymnasium as gym
    if num_envs < 1 or image_size < 8 or action_repeat < 1:
      raise ValueError(f"need num_envs >= 1, image_size >= 8 and action_repeat >= 1, got "
                       f"{num_envs}, {image_size}, {action_repeat}")
    self.image_size, self.action_repeat = image_size, action_repeat
    self.envs = [gym.make("gym_pusht/PushT-v0", obs_type="pixels", render_mode="rgb_array",
                          observation_width=image_size, observation_height=image_size)
                 for _ in range(num_envs)]

  def reset(self, states: np.ndarray) -> tuple[np.ndarray, dict]:
    """Set every environment to ``states [B, 5]``; returns frames ``[B, S, S, 3]`` uint8, info."""
    states = np.asarray(states, np.float64)
    if states.shape != (len(self.envs), 5):
      raise ValueError(f"states must be [{len(self.envs)}, 5], got {states.shape}")
    frames = [env.reset(options={"reset_to_state": s})[0] for env, s in zip(self.envs, states)]
    return np.stack(frames), self._info()

  def step(self, actions: np.ndarray) -> tuple[np.ndarray, dict]:
    """One step (``action_repeat`` control steps of 0.1 s) towards target positions ``[B, 2]``:
    frames ``[B, S, S, 3]``, info with ``coverage`` and ``state`` (``[B]`` / ``[B, 5]``)."""
    actions = np.asarray(actions, np.float64)
    if actions.shape != (len(self.envs), 2) or not np.isfinite(actions).all():
      raise ValueError(f"actions must be finite [{len(self.envs)}, 2], got {actions.shape}")
    for _ in range(self.action_repeat - 1):
      for env, action in zip(self.envs, actions):
        _step_undrawn(env, action)
    frames = [env.step(a)[0] for env, a in zip(self.envs, actions)]
    return np.stack(frames), self._info()

  def _info(self) -> dict:
    coverage, states = [], []
    for env in self.envs:
      inner = env.unwrapped
      coverage.append(inner._get_coverage())
      states.append([*inner.agent.position, *inner.block.position, inner.block.angle])
    return {"coverage": np.array(coverage, np.float32), "state": np.array(states, np.float32)}

  def start(self, states: np.ndarray, context: int
            ) -> tuple[list[np.ndarray], list[np.ndarray], list[dict]]:
    """Reset to ``states [B, 5]`` and keep the agent still for ``context - 1`` steps: the
    ``context`` frames ``[B, S, S, 3]``, the ``context - 1`` still actions ``[B, 2]`` between them
    and the ``context`` infos, as lists (a world model's shared starting context)."""
    frame, info = self.reset(states)
    frames, actions, infos = [frame], [], [info]
    for _ in range(context - 1):
      actions.append(stay_actions(info))
      frame, info = self.step(actions[-1])
      frames.append(frame)
      infos.append(info)
    return frames, actions, infos

  def reset_states(self) -> np.ndarray:
    """``[B, 5]`` ``reset_to_state`` vectors of the current poses (velocities are not kept)."""
    states = self._info()["state"].astype(np.float64)
    return np.stack([reset_state(s[:2], s[2:4], s[4]) for s in states])


def _step_undrawn(env, action: np.ndarray) -> None:
  """One control step of gym-pusht's environment ``env`` towards ``action [2]`` without drawing
  its frame (two thirds of a step's time at 48 px): the held action's control steps before the
  last, whose frames nobody sees. gym-pusht draws in ``step`` when its ``obs_type`` asks for
  pixels, so the step runs as a state observer; the physics is the same. It goes past
  gymnasium's wrappers, whose step count (the time limit's truncation) nothing here reads."""
  inner = env.unwrapped
  obs_type, inner.obs_type = inner.obs_type, "state"
  try:
    inner.step(action)
  finally:
    inner.obs_type = obs_type


def stay_actions(frame_info: dict) -> np.ndarray:
  """Actions ``[B, 2]`` that keep the agent where it is (its current position)."""
  return frame_info["state"][:, :2].astype(np.float64)


def simulate_policy(policy: PolicyFn, states: np.ndarray, steps: int, *, image_size: int,
                    key: jax.Array, context: int = 1, action_repeat: int = 1
                    ) -> dict[str, np.ndarray]:
  """Run ``policy`` closed loop in the simulator from ``states [B, 5]``, each of its actions held
  for ``action_repeat`` control steps (:class:`PushTSimulator`; a step below is one action).

  The first ``context - 1`` steps keep the agent still (so a world model can start from the same
  ``context`` frames and known actions); then the policy runs for ``steps`` steps, called
  on the last ``context`` frames whenever its previous chunk is used up (call ``i`` gets
  ``fold_in(key, i)``). Returns ``frames [B, context+steps, S, S, 3]`` uint8, ``actions
  [B, context-1+steps, 2]``, ``coverage [B, context+steps]`` and ``state [B, context+steps, 5]``."""
  sim = PushTSimulator(len(states), image_size, action_repeat)
  frames, actions, infos = sim.start(states, context)

  def advance(action):
    frame, info = sim.step(action)
    actions.append(np.asarray(action, np.float64))
    frames.append(frame)
    infos.append(info)

  chunk, call = np.zeros((len(states), 0, 2)), 0
  for _ in range(steps):
    if chunk.shape[1] == 0:
      window = np.stack(frames[-context:], 1)
      chunk = np.asarray(policy(to_model(window), jax.random.fold_in(key, call)))
      call += 1
    advance(chunk[:, 0])
    chunk = chunk[:, 1:]
  return {"frames": np.stack(frames, 1), "actions": np.stack(actions, 1).astype(np.float32),
          "coverage": np.stack([i["coverage"] for i in infos], 1),
          "state": np.stack([i["state"] for i in infos], 1)}


@dataclasses.dataclass(frozen=True)
class StayPolicy:
  """Keeps the agent where the newest frame that shows it shows it (a do-nothing baseline).

  A world model may lose the agent from a frame; the policy then holds the position of the
  newest of its ``frames [B, c, H, W, 3]`` that shows one, and only where none does, the frame
  centre (which :func:`centroids` gives for an unseen agent, and which is the goal's centre)."""

  chunk: int = 1

  def __call__(self, frames, key: jax.Array) -> jax.Array:
    del key
    agent, seen = world_centroid(object_masks(jnp.asarray(frames))[1])  # [B, c, 2], [B, c]
    newest = frames.shape[1] - 1 - jnp.argmax(seen[:, ::-1], axis=1)  # all unseen: the newest
    held = jnp.take_along_axis(agent, newest[:, None, None], axis=1)[:, 0]
    return jnp.repeat(held[:, None], self.chunk, axis=1)


def policy_from_spec(spec: str, chunk: int) -> PolicyFn:
  """``push`` / ``push:NOISE`` (:class:`PushPolicy`), ``stay`` (:class:`StayPolicy`),
  ``learned:DIR`` (a :class:`wmjax.policy.LearnedPolicy` saved in ``DIR``; it acts in its own
  chunks), or ``module.path:attribute`` naming any policy callable ``(frames, key) -> [B, k,
  2]``."""
  name, _, argument = spec.partition(":")
  if name == "learned" and argument:
    return load_policy(argument)
  if name == "push":
    return PushPolicy(noise=float(argument or 0.0), chunk=chunk)
  if name == "stay" and not argument:
    return StayPolicy(chunk=chunk)
  if argument and name not in ("push", "stay"):
    try:
      return getattr(importlib.import_module(name), argument)
    except (ImportError, AttributeError) as e:
      raise ValueError(f"policy {spec!r}: cannot import {argument!r} from {name!r}: {e}") from e
  raise ValueError(f"policy spec must be push, push:NOISE, stay, learned:DIR or module:attribute, "
                   f"got {spec!r}")
