"""The one registry of tasks: what a task adds to the generic code, looked up by name there
instead of special-cased.

A task module (``wmjax.tasks.gridworld``, ``wmjax.tasks.pusht``, or one of your own) calls
:func:`register` with a :class:`Task` when it is imported; a config names the module it uses
(``config.task``) and completing the config imports it (:func:`wmjax.config.import_task`). Nothing here
imports a task: a lookup finds what has been registered, and the code below the tasks' layer
(data, eval, train) asks only here. A task adds

* generated datasets (:class:`GeneratedDataset`, keyed by ``config.data.dataset``; the parameters
  are the config section ``config.data.<name>``), which :func:`wmjax.data.sources.dataset_dir`
  makes on first use;
* per-frame metrics of a dataset (:class:`FrameMetrics`, keyed by the dataset's spec name), which
  :func:`wmjax.eval.metrics.frame_metrics` adds to the pixel metrics;
* named rewards (``reward(frames [B, T, H, W, 3], instruction) -> [B]``) for
  :func:`wmjax.eval.rewards.reward_from_spec`;
* control tasks with a true environment (e.g. the gridworld's ``reach``), made from a world
  model's config, on which ``wmjax clone-policy`` and ``wmjax improve`` train policies
  (:func:`control_task`).

How a dataset's records are read (its :class:`wmjax.data.oxe.DatasetSpec`) is the data layer's
own catalogue, :func:`wmjax.data.oxe.register`, which a task's dataset module fills too.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Mapping

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


@dataclasses.dataclass(frozen=True)
class GeneratedDataset:
  """A dataset a task generates: ``prepare(data_dir, params)`` writes it (once per parameter
  set) and returns its builder directory; ``params`` is the dataclass of its parameters, the
  schema of ``config.data.<name>`` (``from_dict``, and ``from_saved`` for a saved config)."""

  params: type
  prepare: Callable[[str, Any], str]


@dataclasses.dataclass(frozen=True)
class Task:
  """What one task module adds; ``module`` is its import name, what ``config.task`` holds."""

  module: str
  datasets: Mapping[str, GeneratedDataset] = dataclasses.field(default_factory=dict)
  frame_metrics: Mapping[str, FrameMetrics] = dataclasses.field(default_factory=dict)
  rewards: Mapping[str, Callable] = dataclasses.field(default_factory=dict)
  control_tasks: Mapping[str, Callable[[Any], Any]] = dataclasses.field(default_factory=dict)


_TASKS: dict[str, Task] = {}


def register(task: Task) -> None:
  """Add ``task`` (a task module calls this when imported; registering a module again replaces
  its entry)."""
  _TASKS[task.module] = task


def task(module: str) -> Task | None:
  """The task registered by ``module``, if it has been imported."""
  return _TASKS.get(module)


def generated_datasets() -> dict[str, GeneratedDataset]:
  """Every registered generated dataset by name."""
  return {name: d for t in _TASKS.values() for name, d in t.datasets.items()}


def frame_metrics_of(dataset: str) -> FrameMetrics | None:
  """The task metrics registered for the dataset spec ``dataset``, if any."""
  return next((t.frame_metrics[dataset] for t in _TASKS.values() if dataset in t.frame_metrics),
              None)


def rewards() -> dict[str, Callable]:
  """Every registered reward by name."""
  return {name: r for t in _TASKS.values() for name, r in t.rewards.items()}


def control_task(name: str, config) -> Any:
  """The control task ``name`` of the registered tasks, made for the world model of ``config``."""
  found = {n: make for t in _TASKS.values() for n, make in t.control_tasks.items()}
  if name not in found:
    raise ValueError(f"no control task {name!r} is registered (the config's task module "
                     f"{config.get('task')!r} offers {sorted(found) or 'none'})")
  return found[name](config)
