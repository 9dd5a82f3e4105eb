"""Load ``ml_collections`` config files: ``path/to/config.py[:arg]`` plus ``key=value`` overrides."""

from __future__ import annotations

import ast
import dataclasses
import difflib
import importlib.util
import os
from typing import Sequence

import ml_collections


class ConfigError(ValueError):
  """A config file or override that cannot be used (unknown key, wrong type, missing file)."""


def _parse_value(text: str):
  try:
    return ast.literal_eval(text)
  except (ValueError, SyntaxError):
    return text


def load_config(spec: str, overrides: Sequence[str] = ()) -> ml_collections.ConfigDict:
  """Run ``get_config(arg)`` of the file in ``spec`` (``file.py`` or ``file.py:arg``).

  ``overrides`` are ``dotted.key=value`` strings; values are Python literals (strings may be
  bare). An unknown key (with the nearest known one) or a value of the wrong type raises
  ValueError.
  """
  path, _, arg = spec.partition(":")
  if not os.path.isfile(path):
    raise ConfigError(f"config file not found: {path!r}")
  module_spec = importlib.util.spec_from_file_location(
      f"wmjax_config_{abs(hash(os.path.abspath(path)))}", path)
  module = importlib.util.module_from_spec(module_spec)
  module_spec.loader.exec_module(module)
  if not hasattr(module, "get_config"):
    raise ConfigError(f"{path} defines no get_config()")
  config = module.get_config(arg) if arg else module.get_config()
  return apply_overrides(config, overrides)


def _check_key(config: ml_collections.ConfigDict, key: str) -> None:
  """ValueError for a key the config does not have, with the nearest known name."""
  node, parts = config, key.split(".")
  for i, part in enumerate(parts):
    if not isinstance(node, ml_collections.ConfigDict) or part not in node:
      where = ".".join(parts[:i])
      known = sorted(node.keys()) if isinstance(node, ml_collections.ConfigDict) else []
      close = difflib.get_close_matches(part, known, n=1)
      hint = (f"; did you mean {where + '.' if where else ''}{close[0]}?" if close else
              f"; {where or 'the config'} has {known}" if known else
              f"; {where} is not a section")
      raise ConfigError(f"unknown config key {key!r}{hint}")
    node = node[part]


def apply_overrides(config: ml_collections.ConfigDict, overrides: Sequence[str]
                    ) -> ml_collections.ConfigDict:
  """Apply ``dotted.key=value`` overrides in place (see :func:`load_config`); returns ``config``."""
  for item in overrides:
    key, sep, value = item.partition("=")
    if not sep:
      raise ConfigError(f"override must be key=value, got {item!r}")
    key = key.strip().removeprefix("--config.").removeprefix("config.")
    _check_key(config, key)
    try:
      config.update_from_flattened_dict({key: _parse_value(value)})
    except (KeyError, AttributeError, TypeError) as e:
      raise ConfigError(f"cannot apply override {item!r}: {e}") from e
  return config


def _dataclass_config(cls, skip: Sequence[str], overrides: dict) -> ml_collections.ConfigDict:
  fields = {f.name: f.default for f in dataclasses.fields(cls) if f.name not in skip}
  unknown = set(overrides) - set(fields)
  if unknown:
    raise ValueError(f"unknown {cls.__name__} fields {sorted(unknown)}; known: {sorted(fields)}")
  fields.update(overrides)
  return ml_collections.ConfigDict(fields)


def model_config(**overrides) -> ml_collections.ConfigDict:
  """Every :class:`wmjax.nn.STDiT` field with its default, updated by ``overrides``."""
  from wmjax.nn.dit import STDiT
  return _dataclass_config(STDiT, ("parent", "name"), overrides)


def sampling_config(**overrides) -> ml_collections.ConfigDict:
  """Every :class:`wmjax.diffusion.SamplerConfig` field with its default, updated by ``overrides``."""
  from wmjax.diffusion.sampling import SamplerConfig
  return _dataclass_config(SamplerConfig, (), overrides)


def optim_config(**overrides) -> ml_collections.ConfigDict:
  """Every :class:`wmjax.train.state.OptimConfig` field with its default, updated by ``overrides``."""
  from wmjax.train.state import OptimConfig
  return _dataclass_config(OptimConfig, (), overrides)
