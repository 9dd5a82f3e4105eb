"""Resuming a run: the config a checkpoint was trained with against the one requested now.

A resumed run continues the run its checkpoint came from, or stops. Changes that cannot alter what
the run computes are accepted (:data:`SAFE_ON_RESUME`: how long it runs, how often it logs,
evaluates and saves, where a new run would have started from, how many data workers read, how the
devices are laid out, how memory is saved: remat and gradient-accumulation micro-batches, which
``train.auto_fit`` may choose, and whether the layers are scanned, their parameters and optimiser
state restacked to match). Any other change (the learning rate, the objective, the data, ...) stops
the run with an error listing each differing key, unless the caller names it (``wmjax train
--allow_config_change KEY[,KEY]``, a key or a whole section such as ``optim``). A change of the
parameters' shapes (the model's width, depth, patch, ...) is always refused: the checkpoint cannot
be loaded into another model.
Accepted changes are printed and recorded in ``WORKDIR/config_changes.jsonl``.
"""

from __future__ import annotations

import json
from typing import Any, Sequence

import ml_collections

from wmjax.errors import RunError

SAFE_ON_RESUME = ("train.num_steps", "train.log_every", "train.eval_every",
                  "train.checkpoint_every", "train.max_checkpoints", "train.eval_windows",
                  "train.auto_fit", "train.memory_budget_gib", "train.init_from", "model.remat",
                  "model.scan_layers", "optim.grad_accum", "data.num_workers", "mesh")

_MISSING = "<absent>"


class ConfigChangeError(RunError):
  """The requested config differs from the checkpoint's in a way the run may not accept."""


def flatten(tree: Any, prefix: str = "") -> dict[str, Any]:
  """``{'a.b': value}`` of a nested dict (lists and tuples are values)."""
  out = {}
  for key, value in tree.items():
    name = f"{prefix}{key}"
    if isinstance(value, dict) and value:
      out.update(flatten(value, name + "."))
    else:
      out[name] = value
  return out


def _with_defaults(saved: dict) -> dict:
  """A saved config with the keys added since it was written at their defaults (so that a new
  key is not a change; ``task`` as :func:`wmjax.config.task_module` infers it for a config saved
  before the key existed); keys since removed are compared as saved."""
  from wmjax.config import ConfigError, complete_config
  try:
    return json.loads(complete_config(saved, strict=False).to_json())
  except ConfigError:  # a section whose shape has changed: compare as saved
    return dict(saved)


def config_changes(saved: dict, requested: ml_collections.ConfigDict | dict
                   ) -> dict[str, tuple[Any, Any]]:
  """``{key: (checkpoint value, requested value)}`` for every leaf that differs."""
  if isinstance(requested, ml_collections.ConfigDict):
    requested = json.loads(requested.to_json())
  old, new = flatten(_with_defaults(saved)), flatten(_with_defaults(requested))
  return {key: (old.get(key, _MISSING), new.get(key, _MISSING))
          for key in sorted(set(old) | set(new)) if old.get(key, _MISSING) != new.get(key, _MISSING)}


def _named(key: str, names: Sequence[str]) -> str | None:
  for name in names:
    name = name.strip().removeprefix("config.")
    if name and (key == name or key.startswith(name + ".")):
      return name
  return None


def _listing(changes: dict) -> str:
  return "\n".join(f"  {key}: {old!r} (checkpoint) -> {new!r} (now)"
                   for key, (old, new) in changes.items())


def check_resume(step: int, saved: dict, requested: ml_collections.ConfigDict,
                 stored_shapes: dict[str, tuple], wanted_shapes: dict[str, tuple],
                 allow: Sequence[str] = ()) -> tuple[dict, dict]:
  """The changes accepted for resuming checkpoint ``step`` and by what (``'safe'`` or the
  ``allow`` name), or :class:`ConfigChangeError` listing what may not change."""
  changes = config_changes(saved, requested)
  if stored_shapes != wanted_shapes:
    differing = sorted(set(stored_shapes) ^ set(wanted_shapes)) or sorted(
        k for k in stored_shapes if stored_shapes[k] != wanted_shapes[k])
    example = differing[0]
    detail = (f"{example}: {stored_shapes.get(example, 'absent')} in the checkpoint, "
              f"{wanted_shapes.get(example, 'absent')} now")
    cause = (f"the config differs in:\n{_listing(changes)}" if changes else
             "the config is unchanged, so the model code must have changed")
    raise ConfigChangeError(
        f"checkpoint {step} cannot be resumed with this config: {len(differing)} of its arrays "
        f"do not fit the train state this config builds (e.g. {detail}); {cause}\n"
        f"A run cannot change the shapes of its parameters or optimiser state: rerun without "
        f"these overrides, or train in a new --workdir.")
  accepted, refused = {}, {}
  for key, change in changes.items():
    by = "safe" if _named(key, SAFE_ON_RESUME) else _named(key, allow)
    if by:
      accepted[key] = by
    else:
      refused[key] = change
  if refused:
    raise ConfigChangeError(
        f"the config differs from the one checkpoint {step} was trained with:\n"
        f"{_listing(refused)}\n"
        f"Rerun without these changes, train in a new --workdir, or accept them with "
        f"--allow_config_change={','.join(refused)} (always accepted on resume: "
        f"{', '.join(SAFE_ON_RESUME)}).")
  return {k: changes[k] for k in accepted}, accepted
