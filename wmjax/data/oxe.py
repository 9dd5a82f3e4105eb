"""Open-X Embodiment (RLDS) dataset specs: where the image, instruction and action live in a step,
and how actions are standardised into the IRASim action spaces.

IRASim action space: RT-1 and Bridge 7-dim ``[dx, dy, dz, droll, dpitch, dyaw, gripper]``;
Language-Table 2-dim ``[dx, dy]``. The published actions are used as they are (RT-1's
``world_vector`` / ``rotation_delta`` / ``gripper_closedness_action``; Bridge's 7-dim action or its
``world_vector`` / ``rotation_delta`` / ``open_gripper``).

A step is the nested dict RLDS gives for one time step (``step['observation']['image']``,
``step['action']['world_vector']``, ...); feature keys are written as ``/``-joined paths below
``steps``. Each dataset may have several published layouts; :func:`resolve_spec` picks the one
whose keys the builder's ``info.features`` holds, or fails listing the keys it expected and found.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Mapping

import numpy as np


def get_path(tree: Mapping[str, Any], path: str) -> Any:
  """``get_path(step, 'observation/image')`` -> ``step['observation']['image']``."""
  for key in path.split("/"):
    tree = tree[key]
  return tree


def decode_instruction(value: Any) -> str:
  """A text feature (bytes / str) or Language-Table's zero-padded int32 UTF-8 byte array -> str."""
  if isinstance(value, (bytes, np.bytes_)):
    return bytes(value).decode("utf-8")
  if isinstance(value, str):
    return value
  array = np.asarray(value)
  if array.dtype.kind in "iu":
    codes = array.reshape(-1)
    codes = codes[: np.argmax(codes == 0)] if (codes == 0).any() else codes
    return bytes(codes.astype(np.uint8).tolist()).decode("utf-8")
  if array.dtype.kind in "SO":
    return decode_instruction(array.reshape(-1)[0]) if array.size else ""
  raise ValueError(f"cannot read an instruction from a value of dtype {array.dtype}")


def concat_actions(*paths: str) -> Callable[[Mapping], np.ndarray]:
  """Standardiser concatenating the features at ``paths`` of batched steps into ``[L, A]``."""
  def standardise(steps):
    parts = [np.asarray(get_path(steps, p), np.float32) for p in paths]
    return np.concatenate([p.reshape(p.shape[0], -1) for p in parts], axis=-1)
  return standardise


@dataclasses.dataclass(frozen=True)
class DatasetSpec:
  """One published layout of an RLDS dataset.

  ``image_key`` / ``instruction_key`` / ``action_keys`` are paths inside a step;
  ``standardise`` maps batched steps (arrays with a leading step axis L) to float32 actions
  ``[L, action_dim]``; ``gripper_dim`` is the index left alone by normalisation (None for none);
  ``resolution`` is (H, W) of the IRASim recipe. ``action_dim`` / ``resolution`` of None are read
  from the features (the action feature's last dimension, the image's native size);
  ``extra_keys`` are per-step arrays carried into windows (e.g. true object positions).
  """

  name: str
  layout: str
  image_key: str
  instruction_key: str
  action_keys: tuple[str, ...]
  standardise: Callable[[Mapping], np.ndarray]
  action_dim: int | None
  gripper_dim: int | None
  resolution: tuple[int, int] | None
  extra_keys: tuple[str, ...] = ()

  @property
  def required_keys(self) -> tuple[str, ...]:
    return (self.image_key, self.instruction_key) + self.action_keys + self.extra_keys

  def actions(self, steps: Mapping) -> np.ndarray:
    """Standardised actions ``[L, action_dim]`` of batched steps."""
    actions = self.standardise(steps)
    if actions.ndim != 2 or actions.shape[1] != self.action_dim:
      raise ValueError(f"{self.name}: standardised actions have shape {actions.shape}, expected "
                       f"[L, {self.action_dim}]")
    return actions


_RT1_ACTION = ("action/world_vector", "action/rotation_delta", "action/gripper_closedness_action")
_BRIDGE_OXE_ACTION = ("action/world_vector", "action/rotation_delta", "action/open_gripper")

SPECS: dict[str, tuple[DatasetSpec, ...]] = {
    "fractal20220817_data": (DatasetSpec(
        "fractal20220817_data", "oxe", "observation/image",
        "observation/natural_language_instruction", _RT1_ACTION, concat_actions(*_RT1_ACTION), 7, 6,
        (256, 320)),),
    "bridge": (
        DatasetSpec("bridge", "oxe", "observation/image", "observation/natural_language_instruction",
                    _BRIDGE_OXE_ACTION, concat_actions(*_BRIDGE_OXE_ACTION), 7, 6, (256, 320)),
        DatasetSpec("bridge", "bridge_v2", "observation/image_0", "language_instruction",
                    ("action",), concat_actions("action"), 7, 6, (256, 320)),
    ),
    "language_table": (DatasetSpec(
        "language_table", "oxe", "observation/rgb", "observation/instruction", ("action",),
        concat_actions("action"), 2, None, (288, 512)),),
}
SPECS["bridge_dataset"] = tuple(dataclasses.replace(s, name="bridge_dataset")
                                for s in SPECS["bridge"])


def register(spec: DatasetSpec) -> None:
  """Add a layout for ``spec.name`` (the synthetic datasets register themselves)."""
  SPECS[spec.name] = tuple(s for s in SPECS.get(spec.name, ()) if s.layout != spec.layout) + (spec,)


def _step_features(features) -> dict[str, Any]:
  """``/``-joined leaf keys below ``steps`` of a TFDS RLDS ``FeaturesDict`` -> leaf features."""
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
  walk(features["steps"], "")
  return leaves


def resolve_spec(name: str, features) -> DatasetSpec:
  """The layout of ``name`` whose keys ``features`` (a builder's ``info.features``) holds."""
  if name not in SPECS:
    raise ValueError(f"unknown dataset {name!r}; known: {sorted(SPECS)}")
  leaves = _step_features(features)
  found = set(leaves)
  for spec in SPECS[name]:
    if set(spec.required_keys) <= found:
      if spec.action_dim is None:
        dim = sum(int(np.prod(leaves[k].shape)) for k in spec.action_keys)
        spec = dataclasses.replace(spec, action_dim=dim)
      if spec.resolution is None:
        spec = dataclasses.replace(spec, resolution=tuple(leaves[spec.image_key].shape[:2]))
      return spec
  expected = "; ".join(f"{s.layout}: {sorted(s.required_keys)}" for s in SPECS[name])
  raise ValueError(f"{name}: the dataset's features match no known layout. Expected the step "
                   f"keys of one of [{expected}]; found {sorted(found)}")
