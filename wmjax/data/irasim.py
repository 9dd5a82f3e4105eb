"""IRASim benchmark data (github.com/bytedance/IRASim) -> the project's RLDS in ArrayRecord
(:mod:`wmjax.data.writer`).

The layout, as IRASim's ``dataset/dataset_2D.py``, ``dataset/dataset_3D.py``, ``util.py``
(``update_paths``) and ``dataset_structure.txt`` read it: one dataset directory of its
``opensource_robotdata`` (``rt1``, ``bridge``, ``languagetable``; ``droid`` reads like RT-1) holds
``annotation/<split>/*.json``, one episode each, for the splits ``train``, ``val`` and ``test``;
the videos and latents the annotation names are relative to the dataset directory.

* Language-Table (``dataset_2D``): ``actions`` ``[T-1, 2]``, ``video_path``
  (``videos/<split>/<id>.mp4``, ``T`` frames), ``latent_video_path`` (a ``.pt`` dict whose
  ``obs`` is ``[T, 4, h, w]``), ``episode_id``. Action ``t`` moves frame ``t`` to ``t+1``.
* RT-1 / Bridge (``dataset_3D``): ``state`` ``[T, S]`` (``S >= 6``: end-effector xyz and
  roll-pitch-yaw first), ``continuous_gripper_state`` ``[T]``, ``videos`` (one
  ``{"video_path": ...}`` per camera; IRASim uses camera 0), ``latent_videos`` (likewise,
  ``.pt`` tensors ``[T, 4, h, w]``), ``episode_id``, ``texts`` (the instruction). IRASim builds
  action ``k-1`` from states ``k-1`` and ``k`` (``accumulate_action: False`` in every config): the
  translation and the roll-pitch-yaw of the rotation relative to the previous end-effector frame
  (``R_prev^T (xyz_k - xyz_prev)``, ``R_prev^T R_k`` with ``R = Rz Ry Rx``) and the gripper
  state ``k``.

Actions are stored unscaled, as the annotation gives them (Language-Table) or as IRASim builds
them before its ``c_act_scaler`` (RT-1 / Bridge); ``dataset_info.json`` records that scale as
``action_scale`` (20 for the arm dimensions, 1 for the gripper; 20 for Language-Table's two).
IRASim's scaling is a normalisation: a checkpoint brought in by ``wmjax import irasim`` holds it
as its action statistics (mean 0, std ``1/scale``), so its model sees exactly what IRASim's did;
a model trained here normalises by the data's own statistics. An episode of ``T`` frames has ``T``
steps; the last step's action (zeros) leads nowhere and enters neither windows nor statistics.
RT-1 / Bridge steps also hold ``observation/state`` (the annotation's state) and
``observation/gripper_state``.
The pre-encoded ``latent_videos`` are not read (they would need torch to unpickle); ``wmjax data
encode`` makes the project's latents from the imported frames.

Splits keep IRASim's names; its evaluation (``configs/evaluation/*``: ``mode: 'test'``) reads
``test``: the short protocol cuts 16-frame windows every 16 frames from frame 0
(``val_start_frame_interval: 16``), the long one rolls out each whole episode — what
``wmjax evaluate`` does with ``data.eval_split='test'`` and ``data.eval_stride=16``. Episodes keep
IRASim's order (annotation files sorted by name). An annotation that is not valid JSON is
skipped and counted (as ``dataset_3D`` does); one without its actions / states is an error
naming the file.
"""

from __future__ import annotations

import functools
import glob
import json
import logging
import os
from typing import Any, Iterator

import numpy as np

from wmjax.data.writer import (check_out, first_frame_shape, step_features, video_steps,
                               write_builder)

log = logging.getLogger(__name__)

# IRASim dataset name -> its dataset class' kind ("2d": Language-Table, "3d": robot-arm states).
DATASETS = {"rt1": "3d", "bridge": "3d", "droid": "3d", "languagetable": "2d"}
SPLITS = ("train", "val", "test")
ARM_SCALE, GRIPPER_SCALE, TABLE_SCALE = 20.0, 1.0, 20.0  # IRASim's c_act_scaler


def action_scale(kind: str) -> list[float]:
  """IRASim's ``c_act_scaler`` per action dimension: ``kind`` '2d' (Language-Table) or '3d'."""
  return [TABLE_SCALE] * 2 if kind == "2d" else [ARM_SCALE] * 6 + [GRIPPER_SCALE]


def euler_to_matrix(rpy: np.ndarray) -> np.ndarray:
  """Roll-pitch-yaw ``[N, 3]`` -> rotation matrices ``[N, 3, 3]`` ``Rz(yaw) Ry(pitch) Rx(roll)``."""
  cos, sin = np.cos(rpy), np.sin(rpy)
  out = np.empty(rpy.shape[:-1] + (3, 3))
  (ca, cb, cc), (sa, sb, sc) = np.moveaxis(cos, -1, 0), np.moveaxis(sin, -1, 0)
  out[..., 0, :] = np.stack([cc * cb, cc * sb * sa - sc * ca, cc * sb * ca + sc * sa], -1)
  out[..., 1, :] = np.stack([sc * cb, sc * sb * sa + cc * ca, sc * sb * ca - cc * sa], -1)
  out[..., 2, :] = np.stack([-sb, cb * sa, cb * ca], -1)
  return out


def matrix_to_euler(rotation: np.ndarray) -> np.ndarray:
  """Rotation matrices ``[N, 3, 3]`` -> roll-pitch-yaw ``[N, 3]`` (inverse of
  :func:`euler_to_matrix`, pitch in ``[-pi/2, pi/2]``; at gimbal lock yaw is 0)."""
  r = rotation
  sy = np.hypot(r[..., 0, 0], r[..., 1, 0])
  singular = sy < 1e-6
  roll = np.where(singular, np.arctan2(-r[..., 1, 2], r[..., 1, 1]),
                  np.arctan2(r[..., 2, 1], r[..., 2, 2]))
  pitch = np.arctan2(-r[..., 2, 0], sy)
  yaw = np.where(singular, 0.0, np.arctan2(r[..., 1, 0], r[..., 0, 0]))
  return np.stack([roll, pitch, yaw], -1)


def relative_actions(state: np.ndarray, gripper: np.ndarray) -> np.ndarray:
  """IRASim's RT-1 / Bridge actions ``[T-1, 7]`` (unscaled) from end-effector states ``[T, >=6]``
  (xyz, roll-pitch-yaw) and gripper states ``[T]``: each step's motion in the previous
  end-effector frame, and the next gripper state."""
  xyz, rotation = state[:, :3], euler_to_matrix(state[:, 3:6])
  previous_t = np.swapaxes(rotation[:-1], -1, -2)
  moved = np.einsum("nij,nj->ni", previous_t, xyz[1:] - xyz[:-1])
  turned = matrix_to_euler(previous_t @ rotation[1:])
  return np.concatenate([moved, turned, gripper[1:, None]], axis=-1)


def _array(annotation: dict, key: str, path: str, ndim: int) -> np.ndarray:
  if key not in annotation:
    raise ValueError(f"{path}: the annotation has no {key!r} (keys: {sorted(annotation)})")
  try:
    values = np.asarray(annotation[key], np.float64)
  except ValueError as error:  # ragged rows
    raise ValueError(f"{path}: {key!r} is not a {ndim}-d array of numbers ({error})") from error
  if values.ndim != ndim:
    raise ValueError(f"{path}: {key!r} has shape {values.shape}, expected {ndim} dimensions")
  return values


def annotation_splits(src: str) -> list[str]:
  """The splits an IRASim dataset directory annotates (``annotation/<split>/``)."""
  return [s for s in SPLITS if os.path.isdir(os.path.join(src, "annotation", s))]


def recognises(src: str) -> bool:
  """Whether ``src`` is an IRASim dataset directory."""
  return bool(annotation_splits(src))


class IRASimDataset:
  """The episodes of one IRASim dataset directory (see the module doc), parsed and checked before
  anything is written."""

  def __init__(self, src: str, dataset: str | None = None, camera: int = 0):
    self.src = os.fspath(src).rstrip("/")
    self.dataset = dataset or os.path.basename(self.src)
    if self.dataset not in DATASETS:
      inside = sorted(d for d in DATASETS if os.path.isdir(os.path.join(self.src, d)))
      hint = (f"it holds the datasets {inside}: import one, e.g. {os.path.join(self.src, inside[0])}"
              if inside else f"name the dataset with --dataset ({'|'.join(DATASETS)})")
      raise ValueError(f"{self.src} is not one of IRASim's dataset directories "
                       f"{sorted(DATASETS)} by name; {hint}")
    self.kind, self.camera = DATASETS[self.dataset], int(camera)
    found = annotation_splits(self.src)
    if not found:
      raise ValueError(f"{self.src} is not an IRASim dataset directory: no annotation/<split>/ "
                       f"for any of the splits {list(SPLITS)}")
    self.skipped: list[str] = []
    self.splits = {s: self._read_split(s) for s in found}

  def _read_split(self, split: str) -> list[dict[str, Any]]:
    paths = sorted(glob.glob(os.path.join(self.src, "annotation", split, "*.json")),
                   key=os.path.basename)
    episodes = []
    for path in paths:
      try:
        with open(path) as f:
          annotation = json.load(f)
      except (json.JSONDecodeError, UnicodeDecodeError):
        self.skipped.append(path)
        continue
      episodes.append(self._episode(annotation, path))
    return episodes

  def _episode(self, annotation: dict, path: str) -> dict[str, Any]:
    """Actions ``[T, A]`` (the last zeros), states, paths and instruction of one annotation."""
    if self.kind == "2d":
      moves = _array(annotation, "actions", path, 2)
      vectors = {}
      video = annotation.get("video_path")
    else:
      state = _array(annotation, "state", path, 2)
      gripper = _array(annotation, "continuous_gripper_state", path, 1)
      if state.shape[1] < 6 or len(gripper) != len(state):
        raise ValueError(f"{path}: 'state' {state.shape} needs >= 6 columns (xyz, roll-pitch-yaw) "
                         f"and one 'continuous_gripper_state' per row (found {len(gripper)})")
      moves = relative_actions(state, gripper)
      vectors = {"state": state, "gripper_state": gripper[:, None]}
      video = self._video_path(annotation, path)
    if not video:
      raise ValueError(f"{path}: the annotation names no video")
    if len(moves) < 1:
      raise ValueError(f"{path}: an episode needs at least one action")
    actions = np.concatenate([moves, np.zeros_like(moves[:1])]).astype(np.float32)
    texts = annotation.get("texts") or []
    texts = [texts] if isinstance(texts, str) else texts
    return {"annotation": path,
            "video": os.path.join(self.src, video),
            "actions": actions, "vectors": vectors,
            "instruction": "; ".join(dict.fromkeys(str(t) for t in texts))}

  def _video_path(self, annotation: dict, path: str) -> str | None:
    """RT-1 / Bridge: the chosen camera's ``videos[camera].video_path``."""
    cameras = annotation.get("videos") or []
    if len(cameras) <= self.camera:
      raise ValueError(f"{path}: no camera {self.camera} among its {len(cameras)} 'videos'")
    return cameras[self.camera].get("video_path")

  @property
  def action_dim(self) -> int:
    return 2 if self.kind == "2d" else 7

  def vector_dims(self) -> dict[str, int]:
    """Width of each per-step state (RT-1 / Bridge: ``state``, ``gripper_state``); every
    annotation must have the first one's."""
    dims = None
    for episode in (e for episodes in self.splits.values() for e in episodes):
      widths = {k: v.shape[1] for k, v in episode["vectors"].items()}
      if dims is not None and widths != dims:
        raise ValueError(f"{episode['annotation']}: states of widths {widths}, but the first "
                         f"annotation's are {dims}")
      dims = widths
    return dims or {}


def _examples(dataset: IRASimDataset, split: str, shape: tuple[int, int]
              ) -> Iterator[tuple[int, dict]]:
  """The split's (key, episode) pairs; ``episode_id``: the annotation file's number (IRASim names
  them by episode), else its place in the split."""
  for index, episode in enumerate(dataset.splits[split]):
    stem = os.path.splitext(os.path.basename(episode["annotation"]))[0]
    yield index, {"steps": video_steps(episode["video"], episode["actions"],
                                       episode["instruction"], shape, episode["vectors"]),
                  "episode_metadata": {"episode_id": int(stem) if stem.isdigit() else index}}


def import_irasim(src: str, out: str, dataset: str | None = None, camera: int = 0) -> str:
  """Write the IRASim dataset directory ``src`` (``.../opensource_robotdata/rt1``; ``dataset``:
  which of :data:`DATASETS` it is, default its name) as the ArrayRecord RLDS builder
  ``irasim_<dataset>`` in ``out`` (must not exist), with the splits it has; ``camera``: the
  annotation's video stored as ``observation/image`` (RT-1 / Bridge). Returns ``out``."""
  out = check_out(out)
  data = IRASimDataset(src, dataset, camera)
  if data.skipped:
    log.warning("skipped %d annotation(s) that are not valid JSON, e.g. %s", len(data.skipped),
                data.skipped[0])
  first = next((e for episodes in data.splits.values() for e in episodes), None)
  if first is None:
    raise ValueError(f"{data.src}: no annotation/<split>/*.json to import")
  shape = first_frame_shape(first["video"])
  splits = {name: functools.partial(_examples, data, name, shape) for name in data.splits}
  scale = action_scale(data.kind)
  return write_builder(out, f"irasim_{data.dataset}",
                       f"IRASim {data.dataset} data {data.src} imported by wmjax",
                       step_features({"image": shape}, data.action_dim, data.vector_dims()),
                       splits, dict(source=os.path.abspath(data.src), dataset=data.dataset,
                                    camera=data.camera, action_scale=scale))
