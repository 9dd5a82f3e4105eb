"""Dataset specs: where the camera(s), instruction and action live in an RLDS step, how actions
are assembled, and how frames are subsampled and fitted — plain data, so a spec is a config.

A step is the nested dict RLDS gives for one time step (``step['observation']['image']``,
``step['action']['world_vector']``, ...); feature keys are written as ``/``-joined paths below
``steps`` (episode-level keys below the episode, e.g. ``episode_metadata/has_image_0``).

Built-in specs (:data:`SPECS`): the Open-X datasets in the IRASim action spaces — RT-1 and Bridge
7-dim ``[dx, dy, dz, droll, dpitch, dyaw, gripper]``, Language-Table 2-dim ``[dx, dy]``; the
published actions are used as they are — and the specs of the datasets the tasks generate, which
their dataset modules register (:func:`register`). A dataset may have several published layouts;
:func:`resolve_spec` picks the first whose keys the builder's ``info.features`` holds, or fails
naming, for the closest layout, each spec field whose keys the features lack, what they hold
instead and the config key that chooses it. Any other RLDS dataset is read by a spec given in
``config.data.spec`` (its schema is :class:`DatasetSpec`, see :func:`spec_config`); ``wmjax data
inspect`` suggests one.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from typing import Any, Mapping, Sequence

import numpy as np

# Action conversions, applied to one action key's values before concatenation.
ACTION_TRANSFORMS = {
    "": lambda a: a,
    "invert": lambda a: 1.0 - a,  # [0, 1] open <-> close
    "negate": lambda a: -a,
    "to_unit": lambda a: (a + 1.0) / 2.0,  # [-1, 1] -> [0, 1]
    "to_signed": lambda a: 2.0 * a - 1.0,  # [0, 1] -> [-1, 1]
    "binarize": lambda a: (a > 0.5).astype(np.float32),
}
INSTRUCTION_ENCODINGS = ("auto", "text", "utf8_codes")
RESIZE_MODES = ("crop", "pad")
MISSING_IMAGE = ("skip", "error")


def get_path(tree: Mapping[str, Any], path: str) -> Any:
  """``get_path(step, 'observation/image')`` -> ``step['observation']['image']``."""
  for key in path.split("/"):
    tree = tree[key]
  return tree


def decode_instruction(value: Any, encoding: str = "auto") -> str:
  """A text feature (bytes / str) or a zero-padded int UTF-8 code array (Language-Table's
  ``int32[512]``) -> str. ``encoding`` ``text`` / ``utf8_codes`` insists on one of the two."""
  array = np.asarray(value)
  is_codes = array.dtype.kind in "iu"
  if encoding == "text" and is_codes or encoding == "utf8_codes" and not is_codes:
    raise ValueError(f"instruction_encoding={encoding!r} but the instruction is an array of "
                     f"dtype {array.dtype}")
  if isinstance(value, (bytes, np.bytes_)):
    return bytes(value).decode("utf-8")
  if isinstance(value, str):
    return value
  if is_codes:
    codes = array.reshape(-1)
    codes = codes[: np.argmax(codes == 0)] if (codes == 0).any() else codes
    return bytes(codes.astype(np.uint8).tolist()).decode("utf-8")
  if array.dtype.kind in "SOU":
    return decode_instruction(array.reshape(-1)[0]) if array.size else ""
  raise ValueError(f"cannot read an instruction from a value of dtype {array.dtype}")


@dataclasses.dataclass(frozen=True)
class DatasetSpec:
  """How to read one RLDS layout (every field is config-friendly; see the module doc).

  ``image_keys``: one step key per camera view; ``"a|b"`` lists fallbacks (the first the dataset
  has is used); several views are tiled left to right, each fitted to ``W / views``.
  ``image_flags``: episode-level booleans saying a view exists (``episode_metadata/has_image_0``);
  left empty, :func:`resolve_spec` finds ``episode_metadata/has_<camera>`` where present. An
  episode whose flag is false is skipped (``missing_image='skip'``, counted in the log) or an
  error (``'error'``); never read as black frames.
  ``instruction_key``: ``""`` for none; ``instruction_encoding``: ``auto`` / ``text`` /
  ``utf8_codes``.
  ``action_keys``: concatenated in this order into float32 ``[L, action_dim]``;
  ``action_transforms``: one name of :data:`ACTION_TRANSFORMS` per key (``""`` = as published),
  or empty for none; ``gripper_dim``: the index normalisation leaves alone (None for none).
  ``frame_step``: keep every k-th step; the k actions in between are summed, except the gripper
  dimension which takes the last one.
  ``resolution``: (H, W) frames are fitted to (None: the camera's native size); ``resize``:
  ``crop`` (centre crop to the aspect ratio, then scale) or ``pad`` (scale to fit, black bars).
  ``action_dim`` None: read from the features. ``extra_keys``: per-step arrays carried into
  windows (e.g. true object positions).
  """

  name: str
  layout: str = "config"
  image_keys: tuple[str, ...] = ("observation/image",)
  image_flags: tuple[str, ...] = ()
  missing_image: str = "skip"
  instruction_key: str = "language_instruction"
  instruction_encoding: str = "auto"
  action_keys: tuple[str, ...] = ("action",)
  action_transforms: tuple[str, ...] = ()
  action_dim: int | None = None
  gripper_dim: int | None = None
  frame_step: int = 1
  resolution: tuple[int, int] | None = None
  resize: str = "crop"
  extra_keys: tuple[str, ...] = ()

  def __post_init__(self):
    for name in ("image_keys", "image_flags", "action_keys", "action_transforms", "extra_keys"):
      value = getattr(self, name)
      if isinstance(value, str):
        value = (value,) if value else ()
      object.__setattr__(self, name, tuple(value))
    if self.resolution is not None:
      object.__setattr__(self, "resolution", tuple(int(v) for v in self.resolution))
    problems = []
    if not self.image_keys:
      problems.append("image_keys is empty")
    if not self.action_keys:
      problems.append("action_keys is empty")
    if self.action_transforms and len(self.action_transforms) != len(self.action_keys):
      problems.append(f"{len(self.action_transforms)} action_transforms for "
                      f"{len(self.action_keys)} action_keys")
    unknown = set(self.action_transforms) - set(ACTION_TRANSFORMS)
    if unknown:
      problems.append(f"unknown action_transforms {sorted(unknown)} (known: "
                      f"{sorted(ACTION_TRANSFORMS)})")
    for field, allowed in (("instruction_encoding", INSTRUCTION_ENCODINGS),
                           ("resize", RESIZE_MODES), ("missing_image", MISSING_IMAGE)):
      if getattr(self, field) not in allowed:
        problems.append(f"{field} must be one of {allowed}, got {getattr(self, field)!r}")
    if int(self.frame_step) < 1:
      problems.append(f"frame_step must be >= 1, got {self.frame_step}")
    if self.resolution is not None and (len(self.resolution) != 2 or min(self.resolution) < 1):
      problems.append(f"resolution must be (H, W), got {self.resolution}")
    if problems:
      raise ValueError(f"dataset spec {self.name!r}: " + "; ".join(problems))

  def actions(self, steps: Mapping) -> np.ndarray:
    """Assembled actions ``[L, action_dim]`` float32 of batched steps (before subsampling)."""
    transforms = self.action_transforms or ("",) * len(self.action_keys)
    parts = []
    for key, transform in zip(self.action_keys, transforms):
      part = np.asarray(get_path(steps, key), np.float32)
      parts.append(ACTION_TRANSFORMS[transform](part.reshape(part.shape[0], -1)))
    actions = np.concatenate(parts, axis=-1).astype(np.float32)
    if self.action_dim is not None and actions.shape[1] != self.action_dim:
      raise ValueError(f"{self.name}: assembled actions have shape {actions.shape}, expected "
                       f"[L, {self.action_dim}]")
    return actions

  def subsample_actions(self, actions: np.ndarray) -> np.ndarray:
    """Actions ``[L, A]`` of raw steps -> ``[ceil(L / frame_step), A]`` (see the class doc)."""
    k = self.frame_step
    if k == 1:
      return actions
    starts = np.arange(0, len(actions), k)
    out = np.add.reduceat(actions, starts, axis=0) if len(actions) else actions
    if self.gripper_dim is not None:
      out[:, self.gripper_dim] = actions[np.minimum(starts + k, len(actions)) - 1,
                                         self.gripper_dim]
    return out.astype(np.float32)

  def to_dict(self) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}

  @classmethod
  def from_dict(cls, data: Mapping[str, Any]) -> "DatasetSpec":
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - fields
    if unknown:
      raise ValueError(f"unknown dataset spec fields {sorted(unknown)}; known: {sorted(fields)}")
    return cls(**data)

  def digest(self) -> str:
    """Identifies what the actions and the chosen episodes depend on (statistics cache key)."""
    keys = ("name", "layout", "image_keys", "image_flags", "missing_image", "action_keys",
            "action_transforms", "gripper_dim", "frame_step")
    text = json.dumps({k: self.to_dict()[k] for k in keys}, sort_keys=True)
    return hashlib.sha1(text.encode()).hexdigest()[:12]


def spec_config(**fields):
  """An ``ml_collections.ConfigDict`` of every :class:`DatasetSpec` field (its schema), default
  values updated by ``fields`` — what ``config.data.spec`` holds (checked when it is used; empty
  ``action_keys`` mean "the built-in spec of ``data.dataset``")."""
  import ml_collections
  defaults = {f.name: f.default for f in dataclasses.fields(DatasetSpec)}
  unknown = set(fields) - set(defaults)
  if unknown:
    raise ValueError(f"unknown dataset spec fields {sorted(unknown)}; known: {sorted(defaults)}")
  return ml_collections.ConfigDict(dict(defaults, name="", **fields))


_RT1_ACTION = ("action/world_vector", "action/rotation_delta", "action/gripper_closedness_action")
_BRIDGE_OXE_ACTION = ("action/world_vector", "action/rotation_delta", "action/open_gripper")

SPECS: dict[str, tuple[DatasetSpec, ...]] = {
    "fractal20220817_data": (DatasetSpec(
        "fractal20220817_data", "oxe", ("observation/image",),
        instruction_key="observation/natural_language_instruction", action_keys=_RT1_ACTION,
        action_dim=7, gripper_dim=6, resolution=(256, 320)),),
    "bridge": (
        DatasetSpec("bridge", "oxe", ("observation/image",),
                    instruction_key="observation/natural_language_instruction",
                    action_keys=_BRIDGE_OXE_ACTION, action_dim=7, gripper_dim=6,
                    resolution=(256, 320)),
        DatasetSpec("bridge", "bridge_v2", ("observation/image_0",), action_dim=7, gripper_dim=6,
                    resolution=(256, 320)),
    ),
    "language_table": (DatasetSpec(
        "language_table", "oxe", ("observation/rgb",), instruction_key="observation/instruction",
        instruction_encoding="utf8_codes", action_dim=2, resolution=(288, 512)),),
}
# `wmjax data import lerobot` output: the chosen camera is observation/image, every other camera
# observation/<name> (data.image_key picks another).
SPECS["lerobot"] = (DatasetSpec("lerobot", "wmjax_import"),)
# `wmjax data import irasim` (builder irasim_<dataset>, IRASim's scaled actions) and `... wpe`
# (WPE's 10-dim Open-X actions, the gripper at 6).
for _name, _dim in (("rt1", 7), ("bridge", 7), ("droid", 7), ("languagetable", 2)):
  SPECS[f"irasim_{_name}"] = (DatasetSpec(f"irasim_{_name}", "wmjax_import", action_dim=_dim,
                                          gripper_dim=6 if _dim == 7 else None),)
SPECS["wpe"] = (DatasetSpec("wpe", "wmjax_import", gripper_dim=6),)
SPECS["bridge_dataset"] = tuple(dataclasses.replace(s, name="bridge_dataset")
                                for s in SPECS["bridge"])


def register(spec: DatasetSpec) -> None:
  """Add a layout for ``spec.name`` (the tasks' generated datasets register theirs when
  imported)."""
  SPECS[spec.name] = tuple(s for s in SPECS.get(spec.name, ()) if s.layout != spec.layout) + (spec,)


# Keys of ``config.data`` that override fields of the dataset's spec.
CONFIG_OVERRIDES = {"image_key": "image_keys", "resize": "resize", "missing_image": "missing_image",
                    "frame_step": "frame_step"}


def specs_from_config(data: Mapping[str, Any]) -> tuple[DatasetSpec, ...]:
  """Candidate specs of a data config (``config.data`` or a mixture member): ``data.spec`` when
  it names action keys, else the built-in layouts of ``data.dataset`` with every field
  ``data.spec`` sets to other than the schema's default applied to each (e.g.
  ``--config.data.spec.instruction_key=KEY`` on a built-in dataset; a field set to the schema's
  own default cannot be told from one left alone, and keeps the built-in value); then the
  overrides
  ``data.image_key`` (str or tuple, ``""`` keeps the spec's), ``data.resize``,
  ``data.missing_image`` and ``data.frame_step`` where set."""
  name = data.get("dataset") or ""
  given = data.get("spec") or {}
  given = dict(given.to_dict() if hasattr(given, "to_dict") else given)
  if given.get("action_keys"):
    candidates = (DatasetSpec.from_dict({**given, "name": given.get("name") or name}),)
  elif name in SPECS:
    defaults = {f.name: f.default for f in dataclasses.fields(DatasetSpec)}
    normal = lambda v: tuple(v) if isinstance(v, list) else v
    changed = {k: v for k, v in given.items()
               if k in defaults and k not in ("name", "action_keys") and normal(v) != defaults[k]}
    candidates = tuple(dataclasses.replace(s, **changed) for s in SPECS[name])
  elif not name:
    raise ValueError("config.data names no dataset: a model-only config (configs/irasim.py "
                     "without a dataset, configs/wpe_600m.py) trains through a recipe that adds "
                     "the data (configs/rt1.py, bridge.py, language_table.py, wpe.py, rlds.py), "
                     "or set config.data.dataset and config.data.builder_dir")
  else:
    raise ValueError(f"unknown dataset {name!r} and no config.data.spec: known datasets are "
                     f"{sorted(SPECS)}; for another RLDS dataset set config.data.spec (run "
                     f"`wmjax data inspect BUILDER_DIR` for a suggestion); a dataset a task "
                     f"generates is known once the task module config.task names is imported "
                     f"(wmjax.config.complete_config(config) imports it)")
  overrides = {}
  for key, field in CONFIG_OVERRIDES.items():
    value = data.get(key)
    if value not in (None, "", ()):
      overrides[field] = (value,) if field == "image_keys" and isinstance(value, str) else value
  return tuple(dataclasses.replace(s, **overrides) for s in candidates)


def feature_leaves(features) -> dict[str, Any]:
  """``/``-joined leaf keys of a TFDS ``FeaturesDict`` -> leaf features; the step features
  (below ``steps``) lose the ``steps/`` prefix, the episode-level ones keep their path."""
  leaves: dict[str, Any] = {}

  def walk(feature, prefix):
    inner = getattr(feature, "feature", None)  # tfds.features.Dataset / Sequence
    if inner is not None and not hasattr(feature, "keys"):
      return walk(inner, prefix)
    if hasattr(feature, "keys"):
      for key in feature.keys():
        walk(feature[key], f"{prefix}/{key}" if prefix else key)
    else:
      leaves[prefix] = feature

  if "steps" not in features.keys():
    raise ValueError(f"not an RLDS dataset: no 'steps' feature (top-level keys: "
                     f"{sorted(features.keys())})")
  for key in features.keys():
    walk(features[key], "" if key == "steps" else key)
  return leaves


def _pick_image(alternatives: str, found: Mapping[str, Any]) -> str | None:
  return next((key for key in alternatives.split("|") if key in found), None)


def is_image_feature(feature) -> bool:
  return type(feature).__name__ == "Image"


def is_text_feature(feature) -> bool:
  """A ``Text`` feature or a scalar string ``Tensor`` (how the published Open-X layouts declare
  their instructions: ``Tensor[] string``)."""
  if type(feature).__name__ == "Text":
    return True
  dtype = getattr(feature, "np_dtype", None)
  return (dtype is not None and np.dtype(dtype).kind in "OSU"
          and not tuple(getattr(feature, "shape", ()) or ()))


def missing_keys(spec: DatasetSpec, steps: Mapping[str, Any]) -> dict[str, tuple[str, ...]]:
  """Field of ``spec`` -> the keys it names that the step features ``steps`` lack (an image
  ``'a|b'`` when neither is there); empty when the spec reads these steps."""
  instruction = (spec.instruction_key,) if spec.instruction_key else ()
  missing = {"image_keys": tuple(a for a in spec.image_keys if _pick_image(a, steps) is None),
             "instruction_key": tuple(k for k in instruction if k not in steps),
             "action_keys": tuple(k for k in spec.action_keys if k not in steps),
             "extra_keys": tuple(k for k in spec.extra_keys if k not in steps)}
  return {field: keys for field, keys in missing.items() if keys}


def _is_instruction(key: str, feature) -> bool:
  """Text, or an integer array of UTF-8 codes named an instruction (Language-Table's)."""
  return is_text_feature(feature) or (
      "instruction" in key and np.dtype(feature.np_dtype).kind in "iu")


# Per key field of a spec: what the dataset offers instead (a predicate on (key, feature)) and
# how a config chooses it.
_KEY_FIELDS = {
    "image_keys": ("cameras", lambda key, f: is_image_feature(f), "config.data.image_key"),
    "instruction_key": ("instructions", _is_instruction,
                        "config.data.spec.instruction_key ('' for none)"),
    "action_keys": ("actions", lambda key, f: key == "action" or key.startswith("action/"),
                    "config.data.spec.action_keys"),
    "extra_keys": ("keys", lambda key, f: True, "config.data.spec.extra_keys"),
}


def _missing_field(field: str, keys: tuple[str, ...], steps: Mapping[str, Any]) -> str:
  """One field's part of resolve_spec's error: what it named, what the steps have instead."""
  kind, offered, how = _KEY_FIELDS[field]
  there = sorted(k for k, f in steps.items() if offered(k, f))
  named = repr(keys[0]) if field == "instruction_key" else repr(list(keys))
  return f"spec.{field} {named} not among the step keys ({kind} there: {there}); set {how}"


def resolve_spec(candidates: str | DatasetSpec | Sequence[DatasetSpec], features) -> DatasetSpec:
  """The first candidate (a dataset name: its built-in layouts) whose keys ``features`` (a
  builder's ``info.features``) holds, with image fallbacks, camera flags, ``action_dim`` and
  ``resolution`` filled in."""
  if isinstance(candidates, str):
    if candidates not in SPECS:
      raise ValueError(f"unknown dataset {candidates!r}; known: {sorted(SPECS)} (or give a "
                       f"spec in config.data.spec)")
    candidates = SPECS[candidates]
  elif isinstance(candidates, DatasetSpec):
    candidates = (candidates,)
  leaves = feature_leaves(features)
  steps = {k: v for k, v in leaves.items() if k.split("/")[0] != "episode_metadata"}
  for spec in candidates:
    if missing_keys(spec, steps):
      continue
    images = tuple(_pick_image(alternatives, steps) for alternatives in spec.image_keys)
    flags = spec.image_flags or tuple(
        f"episode_metadata/has_{key.split('/')[-1]}" for key in images
        if f"episode_metadata/has_{key.split('/')[-1]}" in leaves)
    missing_flags = set(flags) - set(leaves)
    if missing_flags:
      raise ValueError(f"{spec.name}: the image flags {sorted(missing_flags)} are not features "
                       f"of the dataset")
    spec = dataclasses.replace(spec, image_keys=images, image_flags=flags)
    if spec.action_dim is None:
      dim = sum(int(np.prod(steps[k].shape)) for k in spec.action_keys)
      spec = dataclasses.replace(spec, action_dim=dim)
    if spec.resolution is None:
      shapes = [steps[k].shape for k in images]
      if len({s[0] for s in shapes}) > 1:
        raise ValueError(f"{spec.name}: the views {list(images)} differ in height "
                         f"({[s[:2] for s in shapes]}); set a resolution")
      spec = dataclasses.replace(spec, resolution=(shapes[0][0], sum(s[1] for s in shapes)))
    if spec.gripper_dim is not None and not 0 <= spec.gripper_dim < spec.action_dim:
      raise ValueError(f"{spec.name}: gripper_dim {spec.gripper_dim} is outside the "
                       f"{spec.action_dim}-dim actions")
    return spec
  closest = min(candidates, key=lambda s: sum(map(len, missing_keys(s, steps).values())))
  layouts = (f" (closest of the layouts {[s.layout for s in candidates]}: {closest.layout!r})"
             if len(candidates) > 1 else "")
  raise ValueError(f"{closest.name}: the dataset's features match no known layout{layouts}: "
                   + "; ".join(_missing_field(field, keys, steps)
                               for field, keys in missing_keys(closest, steps).items()))
