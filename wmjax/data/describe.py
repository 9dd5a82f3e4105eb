"""``wmjax data inspect``: a prepared TFDS RLDS dataset's splits and features, the keys its spec
reads (and its robot state, which the model does not read) with two decoded instructions per
split, and a suggested
:class:`~wmjax.data.oxe.DatasetSpec` to read it with (a guess to check, printed as config)."""

from __future__ import annotations

import itertools
import re

import numpy as np

from wmjax.config import shipped_config
from wmjax.data import oxe


def _kind(feature) -> str:
  name = type(feature).__name__
  shape = tuple(getattr(feature, "shape", ()) or ())
  dtype = np.dtype(feature.np_dtype).name if hasattr(feature, "np_dtype") else "?"
  return f"{name}{list(shape)} {dtype}"


def _size(feature) -> int:
  return int(np.prod(getattr(feature, "shape", ()) or (1,)))


def suggest_spec(name: str, features) -> oxe.DatasetSpec:
  """A spec guessed from a builder's ``info.features``: one camera (``image``, ``image_0`` or
  ``rgb`` if there is one; :func:`describe` lists the others), a text or UTF-8-code instruction,
  the ``action`` tensor or the float / bool leaves of an ``action`` dict in name order with the
  gripper last (a dataset's ``features.json`` does not keep an order)."""
  leaves = dict(sorted(oxe.feature_leaves(features).items()))
  steps = {k: f for k, f in leaves.items() if not k.startswith("episode_metadata/")}
  cameras = [k for k, f in steps.items() if oxe.is_image_feature(f)]
  if not cameras:
    raise ValueError(f"{name}: no image feature among the steps' keys {sorted(steps)}")
  preferred = [k for k in cameras if k.split("/")[-1] in ("image", "image_0", "rgb")]
  camera = (preferred or cameras)[0]
  texts = [k for k, f in steps.items()
           if oxe.is_text_feature(f) and ("instruction" in k or "language" in k)]
  codes = [k for k, f in steps.items()
           if "instruction" in k and np.dtype(f.np_dtype).kind in "iu" and _size(f) > 1]
  instruction, encoding = ((texts[0], "text") if texts else (codes[0], "utf8_codes") if codes
                           else ("", "auto"))
  actions = [k for k, f in steps.items() if k == "action" or k.startswith("action/")]
  usable = [k for k in actions if np.dtype(steps[k].np_dtype).kind in "fb"
            and "terminate" not in k]
  if not usable:
    raise ValueError(f"{name}: no float / bool action feature among {sorted(steps)}")
  grippers = [k for k in usable if "gripper" in k and _size(steps[k]) == 1]
  ordered = [k for k in usable if k not in grippers] + grippers[:1]
  dim = sum(_size(steps[k]) for k in ordered)
  return oxe.DatasetSpec(name, "suggested", (camera,), instruction_key=instruction,
                         instruction_encoding=encoding, action_keys=tuple(ordered),
                         action_dim=dim, gripper_dim=dim - 1 if grippers else None)


def builtin_spec(name: str, features) -> oxe.DatasetSpec | None:
  """The built-in spec that reads these features, the dataset's own name tried first; None if
  none does."""
  for candidate in [name] * (name in oxe.SPECS) + sorted(set(oxe.SPECS) - {name}):
    try:
      return oxe.resolve_spec(candidate, features)
    except ValueError:
      continue
  return None


STATE_NAMES = r"state|proprio|pose|effector|joint|qpos|qvel|eef|gripper_closed$"


def state_keys(leaves) -> list[str]:
  """The per-step robot state features among ``leaves`` (:func:`oxe.feature_leaves`): numeric
  step keys whose name says ``state``, ``proprio``, ``pose``, ``effector``, ``joint``, ``qpos`` /
  ``qvel``, ``eef`` or ``gripper_closed`` (``observation/state``, Bridge; RT-1's
  ``observation/base_pose_tool_reached`` and ``gripper_closed``; Language-Table's
  ``observation/effector_translation`` and ``effector_target_translation``)."""
  return sorted(k for k, f in leaves.items() if not k.startswith("episode_metadata/")
                and re.search(STATE_NAMES, k.split("/")[-1])
                and not oxe.is_image_feature(f) and np.dtype(f.np_dtype).kind in "fiub")


def _keys_read(spec: oxe.DatasetSpec, leaves) -> str:
  """The step keys a resolved spec reads, by role, and the dataset's robot state, which no
  role reads unless the spec carries it as an extra."""
  encoding = f" ({spec.instruction_encoding})" if spec.instruction_encoding != "auto" else ""
  instruction = spec.instruction_key + encoding if spec.instruction_key else "none"
  extra = f"; extra {', '.join(spec.extra_keys)}" if spec.extra_keys else ""
  states = state_keys(leaves)
  unread = [k for k in states if k not in spec.extra_keys]
  state = ("none" if not states else "as extra" if not unread else
           f"{', '.join(unread)}, not read (the model is conditioned on actions; "
           f"spec.extra_keys carries it into windows)")
  return (f"reads: image {' + '.join(spec.image_keys)}; instruction {instruction}; actions "
          f"{' + '.join(spec.action_keys)}{extra}; state {state}")


def _first_instructions(builder, spec: oxe.DatasetSpec, split: str, count: int = 2) -> list[str]:
  """The decoded instructions of a split's first ``count`` episodes (TFRecord: of those with the
  spec's camera)."""
  from wmjax.data.sources import ArrayRecordEpisodes, tfrecord_episodes
  if builder.info.file_format.value == "array_record":
    episodes = ArrayRecordEpisodes(builder.data_dir, split, spec)
    return [episodes.episode(i, 0, 1).instruction for i in range(min(count, len(episodes)))]
  return [e.instruction for e in itertools.islice(
      tfrecord_episodes(builder.data_dir, split, spec), count)]


def _instruction_lines(builder, spec: oxe.DatasetSpec) -> list[str]:
  """Two decoded instructions per split (what the instruction key reads)."""
  if not spec.instruction_key:
    return []
  splits = [s for s, info in builder.info.splits.items() if info.num_examples]
  try:
    return ["instructions (first two episodes):"] + [
        f"  {split}: " + ", ".join(map(repr, _first_instructions(builder, spec, split)))
        for split in splits]
  except ImportError as e:  # TFRecord without TensorFlow
    return [f"instructions: not read ({e})"]


# fewer episodes than this in a dataset's one split: hold out its last episode instead of 10 %
FEW_EPISODES = 10


def split_overrides(splits) -> tuple[str, str]:
  """The ``data.train_split`` / ``data.eval_split`` overrides of configs/rlds.py (default
  ``train[:90%]`` / ``train[90%:]``) that follow the splits a dataset has (``splits``: name ->
  number of episodes), and a note where training and evaluation must share data: its own
  ``test`` split held out where it has ``train`` and ``test``; of a dataset with one split, the
  last 10 % of its episodes, its last episode when it has fewer than :data:`FEW_EPISODES`, and
  the one episode itself for both when it has one. Returns ``(overrides, note)``."""
  present = {name: count for name, count in splits.items() if count}
  if {"train", "test"} <= set(present):
    return "--config.data.train_split=train --config.data.eval_split=test", ""
  if len(present) != 1:
    return "", ""
  ((only, count),) = present.items()
  if count == 1:
    return (f"--config.data.train_split={only} --config.data.eval_split={only}",
            "one episode in all: training and evaluation share it (the evaluation is then no "
            "held-out measurement)")
  if count < FEW_EPISODES:
    return (f"--config.data.train_split='{only}[:-1]' --config.data.eval_split='{only}[-1:]'",
            f"{count} episodes: the last one is held out for evaluation")
  if only == "train":
    return "", ""
  return f"--config.data.train_split='{only}[:90%]' --config.data.eval_split='{only}[90%:]'", ""


def _convert_first(builder) -> tuple[list[str], str]:
  """For a TFRecord dataset, the lines that convert it to ArrayRecord (training reads episodes
  at random) and the builder directory its training command names then."""
  if builder.info.file_format.value == "array_record":
    return [], str(builder.data_dir)
  converted = str(builder.data_dir).rstrip("/") + "_arrayrecord"
  return ["", f"stored as {builder.info.file_format.value}: training reads ArrayRecord, so "
              f"convert it first:", f"  wmjax data convert {builder.data_dir} {converted}"], converted


def describe(builder) -> str:
  """The text ``wmjax data inspect`` prints for a TFDS builder."""
  info = builder.info
  lines = [f"{info.name} {info.version} ({info.file_format.value}) at {builder.data_dir}",
           "splits: " + ", ".join(f"{s} ({info.splits[s].num_examples} episodes)"
                                  for s in info.splits), "features (steps/ omitted):"]
  leaves = oxe.feature_leaves(info.features)
  width = max(len(k) for k in leaves)
  lines += [f"  {key:<{width}}  {_kind(feature)}" for key, feature in sorted(leaves.items())]
  cameras = sorted(k for k, f in leaves.items() if oxe.is_image_feature(f))
  spec = builtin_spec(info.name, info.features)
  builtin = spec is not None
  spec = spec or suggest_spec(info.name, info.features)
  splits, split_note = split_overrides({name: split.num_examples
                                         for name, split in info.splits.items()})
  convert, builder_dir = _convert_first(builder)
  rlds = shipped_config("rlds.py")
  lines += ["", _keys_read(spec, leaves)] + _instruction_lines(builder, spec) + convert
  if split_note:
    lines += ["", split_note]
  if builtin:
    others = [c for c in cameras if c not in spec.image_keys]
    lines += ["", f"this is the built-in {spec.name!r} spec ({spec.action_dim}-dim actions"
              + (f", gripper dimension {spec.gripper_dim}" if spec.gripper_dim is not None else "")
              + f", camera {', '.join(spec.image_keys)}"
              + (f"; others: {', '.join(others)}, chosen with --config.data.image_key" if others
                 else "") + "); train on it with",
              " ".join(filter(None, [
                  f"  wmjax train --config {rlds} --workdir WORKDIR "
                  f"--config.data.builder_dir={builder_dir} --config.data.dataset={spec.name} "
                  f"--config.model.action_dim={spec.action_dim}", splits]))]
    return "\n".join(lines)
  lines += ["", f"suggested spec (check it; config.data.spec of {rlds}, or overrides):"]
  for key, value in spec.to_dict().items():
    if key in ("name", "layout"):
      continue
    if key == "image_keys" and len(cameras) > 1:
      lines.append(f"  image_keys = {tuple(value)!r}  # cameras: {', '.join(cameras)}")
    else:
      lines.append(f"  {key} = {tuple(value) if isinstance(value, list) else value!r}")
  instruction = spec.instruction_key or "''"
  lines += ["", f"train on it with these overrides of {rlds}:",
            f"  wmjax train --config {rlds} --workdir WORKDIR "
            f"--config.data.builder_dir={builder_dir} --config.data.dataset={info.name} "
            f"--config.data.spec.image_keys=\"{tuple(spec.image_keys)!r}\" "
            f"--config.data.spec.instruction_key={instruction} "
            f"--config.data.spec.action_keys=\"{tuple(spec.action_keys)!r}\" "
            f"--config.data.spec.gripper_dim={spec.gripper_dim} "
            f"--config.model.action_dim={spec.action_dim}" + (f" {splits}" if splits else "")]
  return "\n".join(lines)
