"""Configs: the schema of every section with its defaults, ``ml_collections`` config files
(``path/to/config.py[:arg]``) and ``--config.KEY=VALUE`` overrides.

A config is an ``ml_collections.ConfigDict`` whose sections follow the dataclasses below (and, for
``model``, ``sampling`` and ``data.spec``, the dataclasses they configure: :class:`wmjax.nn.STDiT`,
:class:`wmjax.diffusion.SamplerConfig`, :class:`wmjax.data.oxe.DatasetSpec`; ``data.<generated
dataset>`` follows that dataset's parameters, e.g.
:class:`~wmjax.tasks.gridworld.dataset.GridworldConfig`, of the task module ``task`` names).
:func:`complete_config` imports that task and checks a config against them: an unknown key raises
:class:`ConfigError` naming the nearest valid keys, a value of the wrong type raises naming the type
wanted, and every key left out takes its default here, so code reads ``config.data.train_split`` and
never repeats a default. Config files and overrides are checked when they are loaded
(:func:`load_config`); a config saved by an older version (a workdir's ``config.json``, a
checkpoint's) loads with the keys added since at their defaults (``strict=False`` also keeps keys
since removed).
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import difflib
import importlib
import importlib.util
import os
import sys
import types
import typing
from typing import Any, Literal, Mapping, Sequence

import ml_collections

from wmjax import registry

OVERRIDE_PREFIX = "--config."


class ConfigError(ValueError):
  """A config file or override that cannot be used (unknown key, wrong type, missing file)."""


# --------------------------------------------------------------------------------------------
# Schemas. A field holding a section is declared with ``_section``: its schema is a dataclass,
# named by "module:Class" where importing it here would load the model stack at import time.


def _section(schema: Any, *, optional: bool = False, mapping: bool = False,
             skip: Sequence[str] = (), fill: Mapping[str, Any] | None = None) -> Any:
  """A field holding a sub-section of ``schema`` (a dataclass or ``'module:Class'``);
  ``optional``: absent means None; ``mapping``: ``{name: section}`` (default empty); ``skip``:
  fields of the dataclass that are not config; ``fill``: values of its fields without a
  default."""
  return dataclasses.field(
      default=None, metadata=dict(schema=schema, optional=optional, mapping=mapping,
                                  skip=tuple(skip), fill=dict(fill or {})))


@dataclasses.dataclass(frozen=True)
class CodecConfig:
  """``config.codec``: what the network sees (see :func:`wmjax.codecs.make_codec`)."""

  kind: str = "pixel"  # 'pixel' | 'patch' | 'vae'
  path: str = ""  # vae: a diffusers AutoencoderKL folder
  # vae without files (path is not read): a randomly initialised VAE of a diffusers layout ('sdxl':
  # 4 latent channels; 'sd3': 16) with these block widths (downsampling by 2 ** (len - 1)), the
  # same weights on every load; for trying a latent recipe without the weights (a ``:tiny``
  # profile), its latents mean nothing (wmjax.nn.vae.random_vae)
  random_vae: Literal["", "sdxl", "sd3"] = ""
  random_vae_widths: tuple[int, ...] = (8, 16)
  patch_size: int = 1  # patch
  dtype: str = "float32"  # vae compute dtype
  sample: bool = False  # vae: sample the posterior instead of taking its mean
  chunk: int = 16  # vae: frames encoded / decoded at a time
  scaling_factor: float | None = None  # vae; None: from the VAE's config.json
  shift_factor: float | None = None


@dataclasses.dataclass(frozen=True)
class MixtureMember:
  """One entry of ``config.data.mixture``; a None field takes the data section's value."""

  builder_dir: str = ""
  latents_dir: str = ""
  weight: float = 1.0
  train_split: str | None = None
  eval_split: str | None = None
  spec: Any = _section("wmjax.data.oxe:DatasetSpec", optional=True, fill={"name": ""})
  image_key: str | tuple[str, ...] | None = None
  resize: str | None = None
  missing_image: str | None = None
  frame_step: int | None = None


@dataclasses.dataclass(frozen=True)
class DataConfig:
  """``config.data``: one dataset (or a weighted ``mixture``) and how windows are cut from it.

  ``dataset`` names a built-in layout (Open-X names, ``lerobot``) or a dataset the config's
  ``task`` generates (made in ``data_dir`` with the parameters of ``data.<dataset>``); others
  need ``spec``. ``image_key``, ``resize``, ``missing_image``, ``frame_step`` override the
  spec's where set (``""`` / None: the spec's).
  """

  dataset: str = ""
  data_dir: str = "~/tensorflow_datasets"  # where generated datasets are written
  builder_dir: str = ""  # an ArrayRecord builder directory (`wmjax data convert`)
  latents_dir: str = ""  # pre-encoded latents (`wmjax data encode`) instead of frames
  spec: Any = _section("wmjax.data.oxe:DatasetSpec", optional=True, fill={"name": ""})
  image_key: str | tuple[str, ...] = ""
  resize: str | None = None  # 'crop' | 'pad'
  missing_image: str | None = None  # 'skip' | 'error'
  frame_step: int | None = None
  resolution: tuple[int, int] | None = None  # (H, W); None: the spec's / the camera's
  frames: int = 16  # window length
  train_stride: int = 1
  eval_stride: int = 16
  normalization: str = "mean_std"  # of actions: 'mean_std' | 'bounds' | 'none'
  num_workers: int = 0  # grain worker processes
  train_split: str = "train"
  eval_split: str = "test"
  mixture: Any = _section(MixtureMember, mapping=True)

  @staticmethod
  def extra_sections() -> dict[str, type]:
    """``data.<name>`` sections beyond the fields: the parameters of each generated dataset of
    the tasks imported so far (:func:`wmjax.registry.generated_datasets`; completing a config
    imports its task first)."""
    return {name: d.params for name, d in registry.generated_datasets().items()}


@dataclasses.dataclass(frozen=True)
class DiffusionConfig:
  """``config.diffusion``: the process (:func:`wmjax.diffusion.objectives.make_process`) and how
  training draws noise levels (:func:`wmjax.diffusion.objectives.training_noise`)."""

  kind: str = "gaussian"  # 'gaussian' | 'flow' | 'regression'
  schedule: str = "linear"  # gaussian: 'linear' | 'cosine' | 'sigmoid'
  num_timesteps: int = 1000
  prediction: str = "eps"  # gaussian: 'eps' | 'x0' | 'v'
  # 'per_frame' (diffusion forcing) | 'monotone' (sorted) | 'irasim' | 'autoregressive' (one
  # noised frame after a clean past)
  regime: str = "per_frame"
  num_context: int = 1  # context frames the loss leaves out
  # how a noisy frame's training level is drawn (wmjax.diffusion.LevelSampling): 'default' (the
  # process's own) | 'uniform' | 'logit_normal' (sigmoid(level_loc + level_scale * N(0, 1)))
  level_distribution: str = "default"
  level_loc: float = 0.0
  level_scale: float = 1.0
  # > 0: the loss weighs the values near the objects of the previous (context) frame by
  # 1 + object_weight, grown by object_dilation pixels (wmjax.diffusion.object_weights): small
  # objects that an unweighted MSE barely sees
  object_weight: float = 0.0
  object_dilation: int = 0
  # > 0: this fraction of each batch trains on a last context frame the model generated itself
  # (wmjax.train.self_forcing); the data windows then hold model.num_frames + 1 frames
  self_forcing: float = 0.0
  self_forcing_start: int = 0  # the train step it starts at (before it the model's frames are noise)


@dataclasses.dataclass(frozen=True)
class RolloutConfig:
  """``config.rollout``: blockwise generation, ``context`` frames kept, ``horizon`` new a block."""

  context: int = 1
  horizon: int = 15
  # actions of the IRASim short protocol (1 frame + this many, in chained blocks of at most
  # ``num_frames - 1``); None: one block of the model's window, ``num_frames - 1``
  short_actions: int | None = None


@dataclasses.dataclass(frozen=True)
class OptimConfig:
  """``config.optim``; defaults are IRASim's recipe (paper table 10)."""

  learning_rate: float = 1e-4
  schedule: str = "constant"  # 'constant' | 'warmup' (linear, then constant) | 'cosine'
  warmup_steps: int = 0
  total_steps: int = 300_000  # cosine decay length
  b1: float = 0.9
  b2: float = 0.999
  weight_decay: float = 0.0
  grad_clip: float = 0.1  # global norm; 0 disables
  ema_decay: float = 0.9999
  grad_accum: int = 1  # micro-batches the global batch is cut into inside one step


@dataclasses.dataclass(frozen=True)
class TrainConfig:
  """``config.train``: the training loop."""

  num_steps: int = 300_000
  log_every: int = 100
  checkpoint_every: int = 5_000
  eval_every: int = 5_000  # 0: no evaluation, neither periodic nor at the end
  eval_windows: int = 16  # held-out windows evaluated every eval_every steps
  max_checkpoints: int = 3
  # fit before the first step: compiled memory against the device's limit (or the budget); where
  # it does not fit, the remat and micro-batches predicted fastest of those that do
  auto_fit: bool = True
  memory_budget_gib: float | None = None
  # a workdir whose newest checkpoint's EMA weights (either layer layout; an imported IRASim
  # model's too) start a new run instead of random ones: fine-tuning. Ignored on resume.
  init_from: str = ""


@dataclasses.dataclass(frozen=True)
class Config:
  """The whole config: top-level keys and sections."""

  frame_shape: tuple[int, int, int]  # what the network sees per frame: (H, W, C) after the codec
  batch_size: int  # global
  name: str = ""
  # the task module the run uses (its generated dataset, metrics, rewards), e.g.
  # "wmjax.tasks.gridworld"; imported when the config is completed (import_task); "" for none
  task: str = ""
  codec: Any = _section(CodecConfig)
  data: Any = _section(DataConfig)
  model: Any = _section("wmjax.nn.dit:STDiT", skip=("parent", "name"))
  diffusion: Any = _section(DiffusionConfig)
  sampling: Any = _section("wmjax.diffusion.sampling:SamplerConfig")
  rollout: Any = _section(RolloutConfig)
  optim: Any = _section(OptimConfig)
  train: Any = _section(TrainConfig)
  mesh: tuple[int, ...] = (-1, 1, 1)  # (data, fsdp, tensor); -1: the remaining devices
  seed: int = 0


# --------------------------------------------------------------------------------------------
# Checking a config against the schemas.

_MISSING = dataclasses.MISSING


@dataclasses.dataclass(frozen=True)
class _Field:
  hint: Any
  default: Any
  schema: Any = None  # a sub-section's dataclass
  optional: bool = False
  mapping: bool = False
  skip: tuple[str, ...] = ()
  fill: Mapping[str, Any] = dataclasses.field(default_factory=dict)


def _resolve(schema: Any) -> type:
  if isinstance(schema, str):
    module, _, name = schema.partition(":")
    return getattr(importlib.import_module(module), name)
  return schema


def _fields(cls: type, skip: Sequence[str] = ()) -> dict[str, _Field]:
  hints = typing.get_type_hints(cls)
  out = {}
  for f in dataclasses.fields(cls):
    if f.name in skip or not f.init:
      continue
    default = (f.default if f.default is not _MISSING else
               f.default_factory() if f.default_factory is not _MISSING else _MISSING)
    if "schema" in f.metadata:
      out[f.name] = _Field(Any, None, f.metadata["schema"], f.metadata["optional"],
                           f.metadata["mapping"], f.metadata["skip"], f.metadata["fill"])
    else:
      out[f.name] = _Field(hints.get(f.name, Any), default)
  return out


def _nearest(key: str, known: Sequence[str]) -> list[str]:
  return difflib.get_close_matches(key, list(known), n=3, cutoff=0.6)


def unknown_key_error(key: str, known: Sequence[str], where: str = "") -> ConfigError:
  """The error for ``key`` (under section ``where``), naming the nearest of ``known``."""
  prefix = f"{where}." if where else ""
  close = _nearest(key, known)
  hint = (f"did you mean {' or '.join(prefix + c for c in close)}?" if close else
          f"{where or 'the config'} has {', '.join(sorted(known))}")
  return ConfigError(f"unknown config key {prefix + key!r}; {hint}")


@dataclasses.dataclass(frozen=True)
class _Text:
  """An override's value: the literal it parses as, or (where the key wants a string) its text."""

  text: str

  @property
  def literal(self):
    try:
      return ast.literal_eval(self.text)
    except (ValueError, SyntaxError):
      return self.text


def _describe(hint: Any) -> str:
  if hint is type(None) or hint is None:
    return "None"
  origin = typing.get_origin(hint)
  if origin is Literal:
    return f"one of {', '.join(repr(a) for a in typing.get_args(hint))}"
  if origin in (typing.Union, types.UnionType):
    return " or ".join(_describe(a) for a in typing.get_args(hint))
  if origin is tuple:
    args = typing.get_args(hint)
    if len(args) == 2 and args[1] is Ellipsis:
      return f"a tuple of {_describe(args[0])}"
    return f"a tuple ({', '.join(_describe(a) for a in args)})"
  return getattr(hint, "__name__", str(hint))


_NO = object()


def _typed(value: Any, hint: Any) -> Any:
  """``value`` as ``hint`` (ints are floats where floats are wanted, lists are tuples), or _NO."""
  if isinstance(value, _Text):
    literal = _typed(value.literal, hint)
    return literal if literal is not _NO else _typed(value.text, hint)
  if hint is Any or hint is object:
    return value
  if hint is type(None) or hint is None:
    return None if value is None else _NO
  origin = typing.get_origin(hint)
  if origin is Literal:  # one of the choices, of the choice's own type (True is not 1)
    choices = typing.get_args(hint)
    return value if any(type(value) is type(c) and value == c for c in choices) else _NO
  if origin in (typing.Union, types.UnionType):
    args = typing.get_args(hint)
    if value is None:
      return None if type(None) in args else _NO
    for arg in args:  # an exact type first: 3 stays an int in int | float
      if arg is not type(None) and _typed(value, arg) is not _NO and (
          not isinstance(arg, type) or isinstance(value, arg)):
        return _typed(value, arg)
    for arg in args:
      out = _typed(value, arg)
      if out is not _NO:
        return out
    return _NO
  if origin is tuple:
    if not isinstance(value, (tuple, list)):
      return _NO
    args = typing.get_args(hint)
    each = ([args[0]] * len(value) if len(args) == 2 and args[1] is Ellipsis else
            list(args) if len(args) == len(value) else None)
    if each is None:
      return _NO
    out = tuple(_typed(v, a) for v, a in zip(value, each))
    return _NO if any(v is _NO for v in out) else out
  if origin in (dict, Mapping) or hint in (dict, Mapping):
    return dict(value) if isinstance(value, Mapping) else _NO
  if hint is bool:
    return value if isinstance(value, bool) else _NO
  if hint is int:
    return value if isinstance(value, int) and not isinstance(value, bool) else _NO
  if hint is float:
    return (float(value) if isinstance(value, (int, float)) and not isinstance(value, bool)
            else _NO)
  if isinstance(hint, type):
    return value if isinstance(value, hint) else _NO
  return value


def _plain(value: Any) -> Any:
  if isinstance(value, ml_collections.ConfigDict):
    return value.to_dict()
  if isinstance(value, ml_collections.FieldReference):
    return value.get()
  return value


def _complete(cls: type, values: Any, where: str, strict: bool, skip: Sequence[str] = (),
              construct: bool = False, fill: Mapping[str, Any] | None = None) -> dict:
  """``values`` (a mapping) checked against the dataclass ``cls``, with defaults filled in;
  ``construct``: through ``cls.from_dict`` (its value checks), or for a saved config
  (``strict=False``) ``cls.from_saved`` where the class has one (its defaults for keys an older
  config lacks)."""
  values = _plain(values)
  if values is None:
    values = {}
  if not isinstance(values, Mapping):
    raise ConfigError(f"{where or 'the config'} must be a section (a dict of keys), got "
                      f"{values!r}")
  fields = _fields(cls, skip)
  extra = getattr(cls, "extra_sections", None)
  extra = extra() if extra and any(k not in fields for k in values) else {}
  out, given = {}, {}
  for key, value in values.items():
    name = f"{where}.{key}" if where else key
    if key in extra:
      out[key] = _complete(extra[key], value, name, strict, construct=True)
      continue
    if key not in fields:
      if strict:
        raise unknown_key_error(key, list(fields) + list(extra), where)
      out[key] = _plain(value)
      continue
    field = fields[key]
    value = _plain(value)
    if field.schema is not None:
      schema = _resolve(field.schema)
      if value is None and (field.optional or field.mapping):
        given[key] = {} if field.mapping else None
      elif field.mapping:
        if not isinstance(value, Mapping):
          raise ConfigError(f"{name} must be a dict of sections, got {value!r}")
        given[key] = {k: _complete(schema, v, f"{name}.{k}", strict, field.skip,
                                   fill=field.fill) for k, v in value.items()}
      else:
        given[key] = _complete(schema, value, name, strict, field.skip, fill=field.fill)
    else:
      typed = _typed(value, field.hint)
      if typed is _NO:
        shown = (value.text if isinstance(value, _Text) else
                 f"{value!r} ({type(value).__name__})")
        raise ConfigError(f"config key {name!r} must be {_describe(field.hint)}, got {shown}")
      given[key] = typed
  for key, field in fields.items():
    if key in given:
      continue
    name = f"{where}.{key}" if where else key
    if field.schema is not None:
      given[key] = ({} if field.mapping else None if field.optional else
                    _complete(_resolve(field.schema), {}, name, strict, field.skip,
                              fill=field.fill))
    elif fill and key in fill:
      given[key] = fill[key]
    elif field.default is _MISSING:
      raise ConfigError(f"the config has no {name!r} ({_describe(field.hint)})")
  if construct:
    # a saved config (strict=False) may predate keys whose absence meant something else then
    make = cls.from_saved if not strict and hasattr(cls, "from_saved") else cls.from_dict
    try:
      made = make(given)
    except (TypeError, ValueError) as e:
      raise ConfigError(f"{where or 'the config'}: {e}") from e
    given = {k: getattr(made, k) for k in _fields(cls, skip)}
  for key, field in fields.items():
    if key not in given:
      given[key] = field.default
  return {**{k: given[k] for k in fields}, **out}


# Keys that were removed but that configs saved before may hold: why, by (section, key).
RETIRED_KEYS = {
    ("model", key): "the fused Pallas kernels it chose were slower than XLA in a whole train step "
                    "on a GPU, and were removed (benchmarks/RESULTS.md, 2026-11-26)"
    for key in ("mlp_kernel", "norm_kernel")}


def _without_retired(config: Mapping, strict: bool) -> dict:
  """``config`` without :data:`RETIRED_KEYS`, which a new config (``strict``) may not hold."""
  config = {k: dict(_plain(v)) if isinstance(_plain(v), Mapping) else v
            for k, v in _plain(config).items()}
  for (section, key), why in RETIRED_KEYS.items():
    if key in config.get(section, {}):
      if strict:
        raise ConfigError(f"{section}.{key} no longer exists: {why}")
      del config[section][key]
  return config


def complete_config(config: Mapping | ml_collections.ConfigDict, strict: bool = True
                    ) -> ml_collections.ConfigDict:
  """``config`` checked against :class:`Config` with every key left out at its default, once
  the task it names is imported (:func:`import_task`; ``task`` as :func:`task_module` finds it).

  Unknown keys and values of the wrong type raise :class:`ConfigError`; ``strict=False`` (for a
  config saved by another version) keeps unknown keys as they are instead, but drops those of
  :data:`RETIRED_KEYS`, which a new config may not hold.
  """
  config = _without_retired(config, strict)
  if isinstance(config.get("task"), _Text):  # an override's: the module's name as written
    config["task"] = config["task"].text
  module = task_module(config)
  if module:
    import_task(module)
  completed = ml_collections.ConfigDict(_complete(Config, config, "", strict))
  completed.task = module
  return completed


# --------------------------------------------------------------------------------------------
# The task a config names: a module imported by name (as big_vision imports the evaluators its
# config names), which registers what it adds (wmjax.registry) when imported.

# the tasks that come with wmjax, by the dataset each generates: a config that names no task but
# one of these datasets (one saved before ``task`` existed) uses that task
BUILT_IN_TASKS = {"gridworld": "wmjax.tasks.gridworld", "pusht": "wmjax.tasks.pusht",
                  "metaworld": "wmjax.tasks.metaworld"}


def task_module(config: Mapping) -> str:
  """The task module of a config (complete or as saved): ``task``, else the built-in task that
  generates ``data.dataset`` (``""`` if none)."""
  dataset = (config.get("data") or {}).get("dataset") or ""
  return config.get("task") or BUILT_IN_TASKS.get(dataset, "")


def import_task(module: str) -> registry.Task:
  """Import the task module ``module``; the task it registers. A name that is no module, or a
  module that registers no task, is a :class:`ConfigError`."""
  if not isinstance(module, str) or not all(part.isidentifier() for part in module.split(".")):
    raise ConfigError(f"config key 'task' must name a module, e.g. 'wmjax.tasks.gridworld', "
                      f"got {module!r}")
  try:
    importlib.import_module(module)
  except ModuleNotFoundError as e:
    if not e.name or not (module == e.name or module.startswith(e.name + ".")):
      raise  # a module the task needs is missing, not the task
    close = difflib.get_close_matches(module, BUILT_IN_TASKS.values(), n=1, cutoff=0.6)
    hint = (f"did you mean {close[0]}?" if close else
            f"the built-in tasks are {', '.join(BUILT_IN_TASKS.values())}")
    raise ConfigError(f"config.task {module!r} is no module; {hint}") from None
  task = registry.task(module)
  if task is None:
    raise ConfigError(f"config.task {module!r} is a module but registers no task: a task module "
                      f"calls wmjax.registry.register(Task({module!r}, ...)) when imported")
  return task


def section_config(section: str, **values) -> ml_collections.ConfigDict:
  """Every field of the top-level ``section`` (e.g. ``'model'``) at its default, updated by
  ``values`` (checked: an unknown field names the nearest)."""
  fields = _fields(Config)
  if section not in fields or fields[section].schema is None:
    raise unknown_key_error(section, [k for k, f in fields.items() if f.schema is not None])
  field = fields[section]
  return ml_collections.ConfigDict(
      _complete(_resolve(field.schema), values, section, True, field.skip, fill=field.fill))


def model_config(**values) -> ml_collections.ConfigDict:
  """Every :class:`wmjax.nn.STDiT` field with its default, updated by ``values``."""
  return section_config("model", **values)


def sampling_config(**values) -> ml_collections.ConfigDict:
  """Every :class:`wmjax.diffusion.SamplerConfig` field with its default, updated by ``values``."""
  return section_config("sampling", **values)


def optim_config(**values) -> ml_collections.ConfigDict:
  """Every :class:`OptimConfig` field with its default, updated by ``values``."""
  return section_config("optim", **values)


def codec_config(**values) -> ml_collections.ConfigDict:
  """Every :class:`CodecConfig` field with its default, updated by ``values``."""
  return section_config("codec", **values)


# A latent recipe at smoke-run size: a random VAE of these widths halves the frames' sides.
TINY_VAE_WIDTHS = (8, 16)


def tiny_profile(config: ml_collections.ConfigDict, vae_layout: str, name: str
                 ) -> ml_collections.ConfigDict:
  """A latent recipe (``configs/bridge.py:tiny`` etc.) shrunk, in place, to try on a CPU without
  downloaded weights: frames at 1/8 of the recipe's resolution through a random VAE of
  ``vae_layout`` ('sdxl' or 'sd3', ``codec.random_vae``, no files), a 2-block ST-DiT of width 32
  on 4-frame windows, rollouts of 1 context frame and 3-frame blocks in 2 sampling steps, batch 8,
  20 steps with one evaluation at the end. The data locations, splits, spec, objective and
  optimiser stay the recipe's; ``name`` names the result. What it trains means nothing; it shows
  that the recipe runs."""
  height, width = (side // 8 for side in config.data.resolution)
  shrink = 2 ** (len(TINY_VAE_WIDTHS) - 1)
  config.name = name
  config.codec.update(random_vae=vae_layout, random_vae_widths=TINY_VAE_WIDTHS, path="",
                      dtype="float32")
  config.frame_shape = (height // shrink, width // shrink, config.model.in_channels)
  config.model.update(depth=2, hidden_size=32, num_heads=2, num_frames=4, dtype="float32",
                      remat="none")
  config.data.update(resolution=(height, width), frames=4, eval_stride=4, num_workers=0)
  config.rollout.update(context=1, horizon=3)
  config.sampling.num_steps = 2
  config.batch_size = 8
  config.train.update(num_steps=20, log_every=5, checkpoint_every=20, eval_every=20,
                      eval_windows=4)
  return config


# --------------------------------------------------------------------------------------------
# Config files and overrides.


def shipped_config(name: str) -> str:
  """The config file ``configs/NAME`` of the checkout wmjax is installed from, as an absolute
  path, so that a command printed with it runs from any directory; ``configs/NAME`` where the
  package was installed without its checkout (a wheel ships no ``configs/``)."""
  path = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "configs", name)
  return path if os.path.isfile(path) else os.path.join("configs", name)


def split_overrides(argv: Sequence[str]) -> tuple[list[str], list[str]]:
  """``(overrides, rest)`` of command-line arguments: ``--config.KEY=VALUE`` are overrides (the
  one syntax of the CLI, the benchmarks and the experiments); a bare ``--config.KEY`` is an
  error."""
  overrides, rest = [], []
  for arg in argv:
    if arg.startswith(OVERRIDE_PREFIX):
      if "=" not in arg:
        raise ConfigError(f"override {arg!r} has no value; overrides look like "
                          f"{OVERRIDE_PREFIX}KEY=VALUE")
      overrides.append(arg)
    else:
      rest.append(arg)
  return overrides, rest


def overrides_of(extra: Sequence[str]) -> list[str]:
  """The ``KEY=VALUE`` overrides of a script's leftover arguments ``extra`` (what its parser did
  not know), every one of which must be ``--config.KEY=VALUE``; ConfigError otherwise."""
  overrides, rest = split_overrides(extra)
  if rest:
    raise ConfigError(f"unrecognised arguments {rest}; config overrides look like "
                      f"{OVERRIDE_PREFIX}KEY=VALUE")
  return [o[len(OVERRIDE_PREFIX):] for o in overrides]


OVERRIDES_HELP = (
    "Config overrides: --config.KEY=VALUE, any number, with a Python literal VALUE (strings may "
    "be bare), e.g. --config.train.num_steps=100 --config.optim.learning_rate=3e-4 "
    "--config.model.dtype=bfloat16 --config.mesh='(1,-1,1)'; an unknown key or a value of the "
    "wrong type is an error naming the nearest valid keys.")


def parse_args_with_overrides(parser: argparse.ArgumentParser, argv: Sequence[str] | None = None
                              ) -> tuple[argparse.Namespace, list[str]]:
  """``(parser's arguments, --config.KEY=VALUE overrides)`` of ``argv`` (default: sys.argv):
  the scripts' (benchmarks, experiments) way to take overrides like the ``wmjax`` commands."""
  overrides, rest = split_overrides(sys.argv[1:] if argv is None else argv)
  if not parser.epilog:
    parser.epilog = OVERRIDES_HELP
  return parser.parse_args(rest), overrides


def _set(tree: dict, key: str, value: Any) -> None:
  parts = key.split(".")
  node = tree
  for i, part in enumerate(parts[:-1]):
    child = node.get(part)
    if child is None:
      child = node[part] = {}
    elif not isinstance(child, dict):
      raise ConfigError(f"cannot set {key!r}: {'.'.join(parts[:i + 1])} is a value "
                        f"({child!r}), not a section")
    node = child
  node[parts[-1]] = value


def apply_overrides(config: Mapping | ml_collections.ConfigDict, overrides: Sequence[str],
                    strict: bool = True) -> ml_collections.ConfigDict:
  """``config`` with ``KEY=VALUE`` overrides (``--config.`` prefix optional; values are Python
  literals, strings may be bare), checked and completed (:func:`complete_config`): an unknown key
  names the nearest valid ones, a value of the wrong type the type wanted. Returns a new config.
  ``strict=False`` (a saved config) keeps keys the schema does not know.
  """
  tree = _plain(config)
  tree = dict(tree) if isinstance(tree, Mapping) else tree
  for item in overrides:
    key, sep, value = item.partition("=")
    if not sep:
      raise ConfigError(f"override must be KEY=VALUE, got {item!r}")
    key = key.strip().removeprefix(OVERRIDE_PREFIX).removeprefix("config.")
    if not key or any(not part for part in key.split(".")):
      raise ConfigError(f"override {item!r} names no key")
    _set(tree, key, _Text(value))
  return complete_config(tree, strict)


def load_config(spec: str, overrides: Sequence[str] = ()) -> ml_collections.ConfigDict:
  """Run ``get_config(arg)`` of the file in ``spec`` (``file.py`` or ``file.py:arg``), apply
  ``overrides`` (:func:`apply_overrides`) and check the result against the schema
  (:func:`complete_config`): unknown keys, in the file or an override, and wrong types raise
  :class:`ConfigError`."""
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
  try:
    return apply_overrides(config, overrides)
  except ConfigError as e:
    raise ConfigError(f"{spec}: {e}") from None
