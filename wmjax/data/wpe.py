"""WPE / WorldGym episodes (github.com/world-model-eval/world-model-eval) -> the project's RLDS in
ArrayRecord (:mod:`wmjax.data.writer`).

The layout, as that project's ``download_data.py`` writes it and its ``dataset.py``
(``OpenXMP4VideoDataset``) reads it: ``DIR/<subset>/<split>/NNNNNNNNN.mp4`` beside
``NNNNNNNNN.npz`` whose ``arr_0`` is float32 ``[T, 10]`` (world vector 3, rotation delta 3,
gripper closedness 1, base displacement 2, base rotation 1: the gripper is dimension 6), one
action per frame (action ``t`` moves frame ``t`` to ``t+1``); subsets are Open-X names (``rt_1``,
``bridge_v2``, ...), splits ``train`` and ``test``. There are no instructions.

As WPE's training pools the subsets it names (``--subset_names``, default every directory of
DIR), the splits ``train`` and ``test`` hold the episodes of every chosen subset, subset by subset
in name order and, within one, by file name; ``dataset_info.json`` records how many each subset
gave (``subsets``), so ``train[:N]`` can pick the first. DIR may also be one subset's directory
(holding ``train/`` or ``test/``). As WPE does, an mp4 without its npz or with an npz that does
not load is skipped (counted in the log), and so is an episode of no steps; actions of another
width than the first episode's, or a video shorter than its actions, are errors naming the file;
a video longer than its actions is imported to their length with a warning naming it and
counting the frames left out.
"""

from __future__ import annotations

import functools
import glob
import logging
import os
import zipfile
from typing import Any, Iterator, Sequence

import numpy as np

from wmjax.data.writer import (check_out, first_frame_shape, step_features, video_steps,
                               write_builder)

log = logging.getLogger(__name__)

SPLITS = ("train", "test")


def recognises(src: str) -> bool:
  """Whether ``src`` holds WPE episodes: ``<split>/*.npz`` (one subset's directory) or
  ``<subset>/<split>/*.npz``."""
  return any(glob.glob(os.path.join(src, *subset, split, "*.npz"))
             for subset in ((), ("*",)) for split in SPLITS)


def _load_actions(path: str) -> np.ndarray | None:
  """``arr_0`` of an npz as float32, or None when it does not load (WPE skips those)."""
  try:
    with np.load(path) as npz:
      return np.asarray(npz["arr_0"], np.float32)
  except (OSError, KeyError, ValueError, zipfile.BadZipFile):
    return None


class WPEDataset:
  """The episodes of a WPE data directory (see the module doc), their actions loaded and
  checked before anything is written."""

  def __init__(self, src: str, subsets: Sequence[str] | None = None):
    self.src = os.fspath(src).rstrip("/")
    if not os.path.isdir(self.src):
      raise NotADirectoryError(f"{self.src} is not a directory")
    single = any(os.path.isdir(os.path.join(self.src, s)) for s in SPLITS)
    if single:
      root, available = os.path.dirname(self.src), [os.path.basename(self.src)]
    else:
      root, available = self.src, sorted(d for d in os.listdir(self.src)
                                         if os.path.isdir(os.path.join(self.src, d)))
    unknown = sorted(set(subsets or ()) - set(available))
    if unknown:
      raise ValueError(f"{self.src} has no subset(s) {unknown}; subsets: {available}")
    self.subsets = sorted(subsets) if subsets else available
    self.skipped: dict[str, list[str]] = {"no npz": [], "npz that does not load": [],
                                          "no steps": []}
    self.action_dim: int | None = None
    self.splits: dict[str, list[dict[str, Any]]] = {}
    self.counts: dict[str, dict[str, int]] = {}
    for split in SPLITS:
      parts = {s: self._read(os.path.join(root, s, split)) for s in self.subsets}
      if any(os.path.isdir(os.path.join(root, s, split)) for s in self.subsets):
        self.splits[split] = [e for part in parts.values() for e in part]
        self.counts[split] = {s: len(part) for s, part in parts.items()}
    if not any(self.splits.values()):
      raise ValueError(f"{self.src} holds no WPE episode (<subset>/<split>/NNNNNNNNN.mp4 with "
                       f"its .npz, split in {list(SPLITS)}) in the subsets {self.subsets}")

  def _read(self, directory: str) -> list[dict[str, Any]]:
    episodes = []
    for video in sorted(glob.glob(os.path.join(directory, "*.mp4"))):
      npz = os.path.splitext(video)[0] + ".npz"
      actions = _load_actions(npz) if os.path.isfile(npz) else None
      reason = ("no npz" if not os.path.isfile(npz) else "npz that does not load" if actions is None
                else "no steps" if actions.ndim == 2 and not len(actions) else None)
      if reason:
        self.skipped[reason].append(video)
        continue
      if actions.ndim != 2:
        raise ValueError(f"{npz}: arr_0 has shape {actions.shape}, expected [T, A]")
      if self.action_dim is not None and actions.shape[1] != self.action_dim:
        raise ValueError(f"{npz}: {actions.shape[1]}-dim actions, but the first episode's are "
                         f"{self.action_dim}-dim; every episode needs actions of one width")
      self.action_dim = actions.shape[1]
      episodes.append({"video": video, "actions": actions})
    return episodes


def _examples(dataset: WPEDataset, split: str, shape: tuple[int, int]
              ) -> Iterator[tuple[int, dict]]:
  for index, episode in enumerate(dataset.splits[split]):
    yield index, {"steps": video_steps(episode["video"], episode["actions"], "", shape),
                  "episode_metadata": {"episode_id": index}}


def import_wpe(src: str, out: str, subsets: Sequence[str] | None = None) -> str:
  """Write the WPE data directory ``src`` (``download_data.py``'s output directory, or one subset
  of it) as the ArrayRecord RLDS builder ``wpe`` in ``out`` (must not exist); ``subsets``: the
  subsets pooled (default all). Returns ``out``."""
  out = check_out(out)
  data = WPEDataset(src, subsets)
  for reason, videos in data.skipped.items():
    if videos:
      log.warning("skipped %d video(s) with %s, e.g. %s", len(videos), reason, videos[0])
  shape = first_frame_shape(next(e for s in data.splits.values() for e in s)["video"])
  splits = {name: functools.partial(_examples, data, name, shape) for name in data.splits}
  return write_builder(out, "wpe", f"WPE data {data.src} imported by wmjax",
                       step_features({"image": shape}, data.action_dim), splits,
                       dict(source=os.path.abspath(data.src), subsets=data.counts))
