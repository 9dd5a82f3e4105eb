"""Tiny datasets with the published Open-X Embodiment RLDS feature specs, written by TFDS.

Keys, shapes, dtypes, nesting and action dicts follow the published builders (docs/design.md, Data);
episodes are short and images smooth so the files stay small. Writing TFRecord needs TensorFlow.
"""

from __future__ import annotations

import numpy as np
import tensorflow_datasets as tfds

F = tfds.features


def _image(shape):
  return F.Image(shape=shape, encoding_format="jpeg")


def _flags():
  return {"is_first": np.bool_, "is_last": np.bool_, "is_terminal": np.bool_,
          "reward": F.Scalar(dtype=np.float32)}


FEATURES = {
    "fractal20220817_data": {
        "steps": F.Dataset({
            "action": {
                "base_displacement_vector": F.Tensor(shape=(2,), dtype=np.float32),
                "base_displacement_vertical_rotation": F.Tensor(shape=(1,), dtype=np.float32),
                "gripper_closedness_action": F.Tensor(shape=(1,), dtype=np.float32),
                "rotation_delta": F.Tensor(shape=(3,), dtype=np.float32),
                "terminate_episode": F.Tensor(shape=(3,), dtype=np.int32),
                "world_vector": F.Tensor(shape=(3,), dtype=np.float32),
            },
            "observation": {
                "image": _image((256, 320, 3)),
                "natural_language_embedding": F.Tensor(shape=(512,), dtype=np.float32),
                "natural_language_instruction": F.Text(),
            },
            **_flags(),
        }),
    },
    "bridge": {
        "steps": F.Dataset({
            "action": {
                "open_gripper": np.bool_,
                "rotation_delta": F.Tensor(shape=(3,), dtype=np.float32),
                "terminate_episode": np.float32,
                "world_vector": F.Tensor(shape=(3,), dtype=np.float32),
            },
            "observation": {
                "image": _image((480, 640, 3)),
                "natural_language_embedding": F.Tensor(shape=(512,), dtype=np.float32),
                "natural_language_instruction": F.Text(),
                "state": F.Tensor(shape=(7,), dtype=np.float32),
            },
            **_flags(),
        }),
    },
    "bridge_dataset": {
        "steps": F.Dataset({
            "action": F.Tensor(shape=(7,), dtype=np.float32),
            "discount": F.Scalar(dtype=np.float32),
            "language_instruction": F.Text(),
            "observation": {
                **{f"image_{i}": _image((256, 256, 3)) for i in range(4)},
                "state": F.Tensor(shape=(7,), dtype=np.float32),
            },
            **_flags(),
        }),
        "episode_metadata": {
            "episode_id": np.int32, "file_path": F.Text(), "has_language": np.bool_,
            **{f"has_image_{i}": np.bool_ for i in range(4)},
        },
    },
    "language_table": {
        "steps": F.Dataset({
            "action": F.Tensor(shape=(2,), dtype=np.float32),
            "observation": {
                "effector_target_translation": F.Tensor(shape=(2,), dtype=np.float32),
                "effector_translation": F.Tensor(shape=(2,), dtype=np.float32),
                "instruction": F.Tensor(shape=(512,), dtype=np.int32),
                "rgb": _image((360, 640, 3)),
            },
            **_flags(),
        }),
    },
}

INSTRUCTIONS = ["pick up the red block", "", "push the star to the left corner"]


def _smooth_image(shape, seed):
  h, w, _ = shape
  y, x = np.mgrid[0:h, 0:w]
  base = np.stack([x * 255 // w, y * 255 // h, np.full_like(x, (seed * 37) % 256)], -1)
  return ((base + seed * 13) % 256).astype(np.uint8)


def _random_action(rng, feature):
  if isinstance(feature, dict) or hasattr(feature, "keys"):
    return {k: _random_action(rng, feature[k]) for k in feature.keys()}
  dtype = np.dtype(feature.np_dtype)
  if dtype == np.bool_:
    return bool(rng.integers(0, 2))
  if dtype.kind in "iu":
    return rng.integers(0, 2, feature.shape).astype(dtype)
  return rng.normal(size=feature.shape).astype(dtype)


def make_step(name: str, t: int, length: int, episode: int, rng) -> dict:
  features = FEATURES[name]["steps"].feature
  instruction = INSTRUCTIONS[episode % len(INSTRUCTIONS)]
  step = {"is_first": t == 0, "is_last": t == length - 1, "is_terminal": t == length - 1,
          "reward": float(t == length - 1)}
  obs = {}
  for camera, key in enumerate(features["observation"].keys()):
    feature = features["observation"][key]
    if isinstance(feature, F.Image):  # each camera its own picture
      obs[key] = _smooth_image(feature.shape, 100 * episode + t + 7 * camera)
    elif key == "instruction":  # Language-Table: zero-padded UTF-8 bytes
      codes = np.zeros(512, np.int32)
      codes[:len(instruction.encode())] = list(instruction.encode())
      obs[key] = codes
    elif isinstance(feature, F.Text):
      obs[key] = instruction
    else:
      obs[key] = rng.normal(size=feature.shape).astype(np.float32)
  step["observation"] = obs
  step["action"] = _random_action(rng, features["action"])
  if "language_instruction" in features.keys():
    step["language_instruction"] = instruction
  if "discount" in features.keys():
    step["discount"] = 1.0
  return step


EPISODE_LENGTHS = (5, 3, 7)  # the 3-step episode is shorter than the tests' 4-frame windows


def build(name: str, data_dir: str, file_format: str = "tfrecord",
          absent_cameras: dict[int, tuple[int, ...]] | None = None) -> str:
  """Write the fixture ``name`` (its ``train`` split) under ``data_dir``; returns the builder dir.
  ``absent_cameras``: episode -> camera numbers whose ``has_image_<i>`` is false (and whose
  frames are black, as Open-X stores them)."""
  absent_cameras = absent_cameras or {}

  def _info(self):
    return tfds.core.DatasetInfo(builder=self, features=F.FeaturesDict(FEATURES[name]))

  def _split_generators(self, dl_manager):
    return {"train": self._generate_examples()}

  def _generate_examples(self):
    rng = np.random.default_rng(0)
    for e, length in enumerate(EPISODE_LENGTHS):
      example = {"steps": [make_step(name, t, length, e, rng) for t in range(length)]}
      for i in absent_cameras.get(e, ()):
        for step in example["steps"]:
          step["observation"][f"image_{i}"] = np.zeros_like(step["observation"][f"image_{i}"])
      if "episode_metadata" in FEATURES[name]:
        example["episode_metadata"] = {
            "episode_id": e, "file_path": f"/data/{e}", "has_language": bool(INSTRUCTIONS[e % 3]),
            **{f"has_image_{i}": i not in absent_cameras.get(e, ()) for i in range(4)}}
      yield e, example

  namespace = {"name": name, "VERSION": tfds.core.Version("0.1.0"), "_info": _info,
               "_split_generators": _split_generators, "_generate_examples": _generate_examples}
  builder_cls = type(f"Fixture_{name}", (tfds.core.GeneratorBasedBuilder,), namespace,
                     skip_registration=True)
  builder = builder_cls(data_dir=data_dir, file_format=file_format)
  builder.download_and_prepare()
  return str(builder.data_dir)
