"""MetaWorld (Farama, MuJoCo 3): a Sawyer arm with a gripper, rendered from several cameras.

:class:`ArmSimulator` wraps one MetaWorld v3 task for data and evaluation: a start state (the
arm's initial hand position and the task's object / goal placement, :func:`random_start_states`)
instead of MetaWorld's own global random draws, each action held ``action_repeat`` control steps
with one frame per action, every camera of ``views`` rendered at ``image_size`` square
(headless through EGL; shadows, reflections, the skybox and multisampling off: 13 ms a 48x48
render instead of 150 on a 2-core CPU), and the simulator state for an exact replay
(:meth:`ArmSimulator.sim_state` / :meth:`ArmSimulator.restore`).

The state a policy acts on, :data:`STATE_SIZE` numbers: the hand (tool centre point) ``x, y, z``
and the task object's position ``x, y, z`` (the button's / drawer handle's site), in metres.
MetaWorld's scripted experts read exactly these two from their observation vector
(:func:`expert_observation`), so they run on a state read off frames as on the simulator's.

Actions are MetaWorld's: ``[dx, dy, dz, grip]`` in ``[-1, 1]``, the hand's target moving by
``0.01 * d`` metres a control step.

Importing this module sets ``MUJOCO_GL=egl`` unless it is set: MuJoCo picks its OpenGL platform
when it is first imported, so import this module (or set the variable) before ``mujoco`` or
``metaworld`` is imported elsewhere. MuJoCo's EGL context crashes the process (a segmentation
fault) where TensorFlow has been imported: :class:`ArmSimulator` refuses to start there, and the
dataset builder simulates in spawned worker processes instead.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import sys
from typing import Callable

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering: before mujoco is imported

# task -> (its scripted expert in metaworld.policies, what the object is)
TASKS = {
    "button-press-v3": ("SawyerButtonPressV3Policy", "button"),
    "drawer-open-v3": ("SawyerDrawerOpenV3Policy", "drawer handle"),
}
# the cameras of MetaWorld's Sawyer scenes (``topview`` third person; ``gripperPOV`` on the wrist)
CAMERAS = ("topview", "corner", "corner2", "corner3", "corner4", "behindGripper", "gripperPOV")
ACTION_DIM = 4
STATE_SIZE = 6  # hand x, y, z; object x, y, z
# how far (metres) a start state's hand lies from the task's own initial hand position, per axis
HAND_SPREAD = (0.08, 0.05, 0.05)

# (observation, rng) -> action [4]
Policy = Callable[[np.ndarray, np.random.Generator], np.ndarray]


def check_installed() -> None:
  """ImportError naming the extra to install when MetaWorld is missing."""
  try:
    import metaworld  # noqa: F401
    import mujoco  # noqa: F401
  except ImportError as e:
    raise ImportError(f'the MetaWorld simulator needs its extra: pip install -e ".[metaworld]" '
                      f'(or pip install "wmjax[metaworld]"; {e})') from e


def check_task(task: str) -> None:
  if task not in TASKS:
    raise ValueError(f"unknown MetaWorld task {task!r}; valid tasks: {', '.join(TASKS)}")


def check_views(views) -> tuple[str, ...]:
  views = tuple(views)
  unknown = [v for v in views if v not in CAMERAS]
  if not views or unknown:
    raise ValueError(f"unknown camera(s) {unknown or '(none given)'}; valid cameras: "
                     f"{', '.join(CAMERAS)}")
  return views


def _make_env(task: str):
  check_installed()
  from metaworld.env_dict import ALL_V3_ENVIRONMENTS
  env = ALL_V3_ENVIRONMENTS[task]()
  env._partially_observable = False  # the goal in the observation, as the experts expect
  env._set_task_called = True
  env._freeze_rand_vec = True  # the start state sets the placement
  env.max_path_length = 10**9  # episodes are as long as the data asks
  return env


@dataclasses.dataclass(frozen=True)
class StartSpace:
  """What a start state holds: the hand's initial position (``hand_init`` +- :data:`HAND_SPREAD`)
  then the task's placement vector (MetaWorld's ``_random_reset_space``: object, and goal where
  the task has one), ``low`` / ``high`` ``[D]`` each."""

  low: np.ndarray
  high: np.ndarray

  @classmethod
  @functools.cache  # building the scene to read it takes a fifth of a second
  def of(cls, task: str) -> "StartSpace":
    env = _make_env(task)
    hand, space = np.asarray(env.hand_init_pos, np.float64), env._random_reset_space
    spread = np.asarray(HAND_SPREAD)
    env.close()
    low = np.concatenate([hand - spread, space.low])
    high = np.concatenate([hand + spread, space.high])
    low.flags.writeable = high.flags.writeable = False  # one instance, shared by every caller
    return cls(low, high)


def random_start_states(space: StartSpace, rng: np.random.Generator, count: int) -> np.ndarray:
  """``[count, D]`` start states uniform in ``space`` (float64)."""
  return rng.uniform(space.low, space.high, size=(count, len(space.low)))


class ArmSimulator:
  """One MetaWorld task rendering ``views`` at ``image_size`` square, RGB uint8."""

  def __init__(self, task: str, views=("topview", "gripperPOV"), image_size: int = 48,
               action_repeat: int = 4):
    check_task(task)
    if "tensorflow" in sys.modules:
      raise RuntimeError("MuJoCo's EGL rendering crashes a process that has imported TensorFlow; "
                         "simulate in a fresh process (a spawned worker) instead")
    self.views, self.image_size, self.action_repeat = check_views(views), image_size, action_repeat
    import mujoco
    self._mujoco = mujoco
    self.task, self.env = task, _make_env(task)
    model = self.env.model
    model.vis.quality.offsamples = 0
    model.vis.global_.offwidth = max(model.vis.global_.offwidth, image_size)
    model.vis.global_.offheight = max(model.vis.global_.offheight, image_size)
    self._renderer = mujoco.Renderer(model, image_size, image_size)
    for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION,
                 mujoco.mjtRndFlag.mjRND_SKYBOX):
      self._renderer.scene.flags[flag] = 0
    self._obs = None

  def close(self) -> None:
    self._renderer.close()
    self.env.close()

  def reset(self, start_state) -> np.ndarray:
    """Place the arm and the objects as ``start_state [D]`` says; returns the observation."""
    start_state = np.asarray(start_state, np.float64)
    self.env.hand_init_pos = start_state[:3].copy()
    self.env._last_rand_vec = start_state[3:].copy()
    self._obs, _ = self.env.reset()
    return self._obs

  def step(self, action) -> tuple[np.ndarray, bool]:
    """Hold ``action [4]`` (clipped to [-1, 1]) for ``action_repeat`` control steps; returns the
    observation and whether the task counts as solved at the end."""
    action = np.clip(np.asarray(action, np.float64), -1.0, 1.0)
    success = False
    for _ in range(self.action_repeat):
      self._obs, _, _, _, info = self.env.step(action)
      success = bool(info["success"])
    return self._obs, success

  def state(self) -> np.ndarray:
    """``[STATE_SIZE]`` hand and object positions (metres, float32)."""
    return np.concatenate([self.env.tcp_center, self._obs[4:7]]).astype(np.float32)

  def render(self) -> np.ndarray:
    """``[V, S, S, 3]`` uint8: one image per camera of ``views``."""
    images = []
    for camera in self.views:
      self._renderer.update_scene(self.env.data, camera=camera)
      images.append(self._renderer.render().copy())
    return np.stack(images)

  def pixel(self, point, camera: str) -> np.ndarray:
    """Where the 3-D ``point`` lands in ``camera``'s image: ``(col, row)`` in pixels of an
    ``image_size`` render (row 0 at the top)."""
    model, data = self.env.model, self.env.data
    cam = model.camera(camera).id
    rotation = data.cam_xmat[cam].reshape(3, 3)
    local = rotation.T @ (np.asarray(point, np.float64) - data.cam_xpos[cam])  # x right, y up, -z
    focal = self.image_size / 2 / np.tan(np.deg2rad(model.cam_fovy[cam]) / 2)
    col = self.image_size / 2 + focal * local[0] / -local[2]
    row = self.image_size / 2 - focal * local[1] / -local[2]
    return np.array([col, row], np.float32)

  def sim_state(self) -> np.ndarray:
    """Everything an exact replay needs, flat (float64): ``qpos``, ``qvel``, the hand target
    (mocap position and quaternion)."""
    data = self.env.data
    return np.concatenate([data.qpos, data.qvel, data.mocap_pos.reshape(-1),
                           data.mocap_quat.reshape(-1)])

  def restore(self, sim_state) -> None:
    """Put the simulator back in a state :meth:`sim_state` returned."""
    data, model = self.env.data, self.env.model
    sim_state = np.asarray(sim_state, np.float64)
    sizes = np.cumsum([model.nq, model.nv, data.mocap_pos.size])
    qpos, qvel, mocap_pos, mocap_quat = np.split(sim_state, sizes)
    data.mocap_pos[:] = mocap_pos.reshape(data.mocap_pos.shape)
    data.mocap_quat[:] = mocap_quat.reshape(data.mocap_quat.shape)
    self.env.set_state(qpos, qvel)
    self._obs = self.env._get_obs()


# ----------------------------------------------------------------------------------- policies


def expert_observation(state) -> np.ndarray:
  """A MetaWorld observation vector ``[39]`` holding what the scripted experts read: the hand
  (``state[:3]``) and the object (``state[3:6]``); the rest is zero."""
  obs = np.zeros(39, np.float64)
  obs[:3], obs[4:7] = state[:3], state[3:6]
  return obs


@dataclasses.dataclass
class Expert:
  """MetaWorld's scripted expert of ``task`` on a state ``[6]``, with Gaussian action noise of
  standard deviation ``noise`` (the result clipped to [-1, 1])."""

  task: str
  noise: float = 0.0

  def __post_init__(self):
    check_task(self.task)
    import warnings

    import metaworld.policies
    warnings.filterwarnings("ignore", message="Constant\\(s\\) may be too high")
    self._policy = getattr(metaworld.policies, TASKS[self.task][0])()

  def __call__(self, state, rng: np.random.Generator) -> np.ndarray:
    action = np.asarray(self._policy.get_action(expert_observation(state)), np.float64)
    if self.noise > 0:
      action = action + rng.normal(0.0, self.noise, action.shape)
    return np.clip(action, -1.0, 1.0).astype(np.float32)


@dataclasses.dataclass
class RandomAgent:
  """A new random move each ``hold`` actions: a direction uniform in ``[-1, 1]^3`` and a random
  grip; it touches the objects from every side, or passes them by."""

  hold: int = 2
  _count: int = 0
  _action: np.ndarray | None = None

  def __call__(self, state, rng: np.random.Generator) -> np.ndarray:
    del state
    if self._action is None or self._count % self.hold == 0:
      self._action = rng.uniform(-1.0, 1.0, ACTION_DIM).astype(np.float32)
    self._count += 1
    return self._action


def idle(state, rng: np.random.Generator) -> np.ndarray:
  """Stand still, gripper open: nothing in the scene moves."""
  del state, rng
  return np.array([0.0, 0.0, 0.0, -1.0], np.float32)


def policy_from_spec(spec: str, task: str) -> Policy:
  """``expert`` or ``expert:NOISE`` (MetaWorld's scripted expert with Gaussian action noise),
  ``random`` or ``idle``."""
  name, _, argument = spec.partition(":")
  if name == "expert":
    return Expert(task, float(argument or 0.0))
  if name == "random" and not argument:
    return RandomAgent()
  if name == "idle" and not argument:
    return idle
  raise ValueError(f"policy must be expert, expert:NOISE, random or idle, got {spec!r}")
