"""Tasks: the simulators wmjax generates data from and what is particular to each (dataset
builder, policies, metrics, rewards, evaluation). A task module registers a
:class:`wmjax.registry.Task` when it is imported; a config names the module it uses
(``config.task``), and the entry points (the ``wmjax`` commands, :func:`wmjax.train.loop.train`,
:func:`wmjax.eval.evaluate.evaluate_checkpoint`) import it with :func:`with_task`. This package
imports no task of its own accord.

* :mod:`wmjax.tasks.gridworld` — WPE's gridworld of coloured squares;
* :mod:`wmjax.tasks.pusht` — Push-T (gym-pusht).
"""

from __future__ import annotations

import difflib
import importlib
from typing import Mapping

import ml_collections

from wmjax import registry
from wmjax.config import ConfigError, complete_config

# the tasks that come with wmjax (``wmjax data prepare`` offers their datasets)
BUILT_IN = ("wmjax.tasks.gridworld", "wmjax.tasks.pusht")


def import_task(module: str) -> registry.Task:
  """Import the task module ``module``; the task it registers. A name that is no module, or a
  module that registers no task, is a :class:`~wmjax.config.ConfigError`."""
  try:
    importlib.import_module(module)
  except ModuleNotFoundError as e:
    if not e.name or not (module == e.name or module.startswith(e.name + ".")):
      raise  # a module the task needs is missing, not the task
    close = difflib.get_close_matches(module, BUILT_IN, n=1, cutoff=0.6)
    hint = f"did you mean {close[0]}?" if close else f"the built-in tasks are {', '.join(BUILT_IN)}"
    raise ConfigError(f"config.task {module!r} is no module; {hint}") from None
  task = registry.task(module)
  if task is None:
    raise ConfigError(f"config.task {module!r} is a module but registers no task: a task module "
                      f"calls wmjax.registry.register(Task({module!r}, ...)) when imported")
  return task


def built_in_task_of(dataset: str) -> str:
  """The built-in task that generates ``dataset`` (``""`` if none): a config saved before
  ``config.task`` existed names its task by its dataset alone."""
  return next((module for module in BUILT_IN if dataset in import_task(module).datasets), "")


def task_module(config: Mapping) -> str:
  """The task module of a config (complete or as saved): ``task``, else the built-in task that
  generates ``data.dataset``."""
  return config.get("task") or built_in_task_of((config.get("data") or {}).get("dataset") or "")


def with_task(config: Mapping, strict: bool = True) -> ml_collections.ConfigDict:
  """``config`` with its task imported (:func:`task_module`, written into ``task``) and then
  completed against the schema, the task's sections (``data.<generated dataset>``) included;
  ``strict=False`` for a saved config (:func:`wmjax.config.complete_config`)."""
  module = task_module(config)
  if module:
    import_task(module)
  completed = complete_config(config, strict)
  completed.task = module
  return completed
