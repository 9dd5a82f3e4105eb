"""What tasks add to the generic code, looked up by name instead of special-cased there:

* per-frame metrics of a dataset (:class:`FrameMetrics`, keyed by the dataset's spec name), which
  :func:`wmjax.eval.metrics.frame_metrics` adds to the pixel metrics;
* named rewards (``reward(frames [B, T, H, W, 3], instruction) -> [B]``) for
  :func:`wmjax.eval.rewards.reward_from_spec`.

Generated datasets register with :func:`wmjax.data.sources.register_generated` and dataset specs
with :func:`wmjax.data.oxe.register`. Importing :mod:`wmjax.tasks` registers every built-in task;
the lookups here and in :mod:`wmjax.data.sources` do it on first use
(:func:`load_built_in_tasks`), so that the code below the tasks' layer, which never imports
them by name, still finds them. A task of your own registers the same way, when imported.
"""

from __future__ import annotations

import dataclasses
import importlib
from typing import Callable, Mapping

import numpy as np

# (pred, truth [E, T, H, W, 3] uint8, per-frame extras {name: [E, T, ...]}) -> {name: [E, T]}
FrameFn = Callable[[np.ndarray, np.ndarray, Mapping[str, np.ndarray]], dict[str, np.ndarray]]
# the same inputs -> object masks [E, T, H, W] (bool), or None when the extras lack what they need
MaskFn = Callable[[np.ndarray, np.ndarray, Mapping[str, np.ndarray]], "np.ndarray | None"]


@dataclasses.dataclass(frozen=True)
class FrameMetrics:
  """A task's own per-frame metrics: ``compute`` returns them (``{}`` when the extras lack what
  they need, e.g. in a mixture), ``object_masks`` the pixels the masked MSE is taken over (when
  the data brings no masks of its own); ``lower_is_better`` orders them in reports and
  ``headline`` names the one whose per-frame curve a report shows."""

  compute: FrameFn
  lower_is_better: Mapping[str, bool]
  headline: str
  object_masks: MaskFn | None = None


_FRAME_METRICS: dict[str, FrameMetrics] = {}
_REWARDS: dict[str, Callable] = {}


def load_built_in_tasks() -> None:
  """Import :mod:`wmjax.tasks`, whose packages register here (once; later calls cost nothing)."""
  importlib.import_module("wmjax.tasks")


def register_frame_metrics(dataset: str, metrics: FrameMetrics) -> None:
  """Score frames of the dataset whose spec is named ``dataset`` with ``metrics`` too."""
  _FRAME_METRICS[dataset] = metrics


def frame_metrics_of(dataset: str) -> FrameMetrics | None:
  """The task metrics registered for ``dataset``, if any."""
  load_built_in_tasks()
  return _FRAME_METRICS.get(dataset)


def register_reward(name: str, reward: Callable) -> None:
  """Make ``name`` a reward spec (``--reward NAME``)."""
  _REWARDS[name] = reward


def rewards() -> dict[str, Callable]:
  """Every registered reward by name."""
  load_built_in_tasks()
  return dict(_REWARDS)
