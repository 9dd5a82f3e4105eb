"""LeRobot datasets (``meta/info.json``, ``data/**/*.parquet``, ``videos/**/*.mp4``) -> the
project's RLDS in ArrayRecord, read with pyarrow and :func:`wmjax.data.videoio.read_video` (no
torch, no ``lerobot`` package).

Both layouts are read: v2.x (one parquet and one mp4 per camera per episode, episode metadata in
``meta/episodes.jsonl``) and v3 (several episodes per file, episode metadata in
``meta/episodes/**/*.parquet`` with each camera's ``from_timestamp`` in its video file). A frame
row's ``action`` becomes the step's action: LeRobot records the action taken at that frame, which
leads to the next one, the RLDS alignment. Cameras are ``video`` (or ``image``) features.

The output is a TFDS builder directory named ``lerobot`` (built-in spec ``lerobot``):
``steps/observation/image`` (PNG) is the chosen camera (default the first), every other camera
``steps/observation/<name>`` (``observation.images.wrist`` -> ``wrist``, see :func:`camera_name`),
``steps/observation/state`` the ``observation.state`` where present, ``steps/action`` float32
``[A]`` (the ``action`` feature, or the one named), ``steps/language_instruction`` the episode's
task(s), ``is_first`` / ``is_last`` / ``is_terminal``; splits as ``info.json`` lists them
(``"train": "0:50"``), episodes in the source's order. Each video file is decoded once, front to
back (:class:`wmjax.data.videoio.VideoStream`), holding one episode's frames per camera.
"""

from __future__ import annotations

import functools
import glob
import io
import json
import os
import re
from typing import Any

import numpy as np
from PIL import Image

from wmjax.data.writer import check_out, episode_steps, step_features, write_builder

VERSIONS = ("v2", "v3")


def camera_name(key: str) -> str:
  """``observation.images.wrist`` -> ``wrist`` (a valid feature name; ``observation.image`` ->
  ``image_camera``, as ``image`` is the chosen camera's place)."""
  name = re.sub(r"\W", "_", key.removeprefix("observation.images.").removeprefix("observation."))
  return "image_camera" if name == "image" else name


def _info_path(src: str) -> str:
  return os.path.join(src, "meta", "info.json")


def recognises(src: str) -> bool:
  """Whether ``src`` holds a LeRobot dataset (it has ``meta/info.json``)."""
  return os.path.isfile(_info_path(src))


class LeRobotDataset:
  """The parts of a local LeRobot dataset the importer needs (see the module doc)."""

  def __init__(self, src: str, action_key: str = "action"):
    self.src, self.action_key = os.fspath(src), action_key
    if not recognises(self.src):
      raise ValueError(f"{src} is not a LeRobot dataset: no meta/info.json")
    with open(_info_path(self.src)) as f:
      self.info = json.load(f)
    version = str(self.info.get("codebase_version", ""))
    self.version = version.split(".")[0]
    if self.version not in VERSIONS:
      raise ValueError(f"{src}: LeRobot codebase_version {version!r} is not supported (v2.x or "
                       f"v3.x)")
    features = self.info.get("features", {})
    self.cameras = [k for k, v in features.items() if v.get("dtype") in ("video", "image")]
    if action_key not in features or not self.cameras:
      vectors = sorted(k for k, v in features.items() if v.get("dtype", "").startswith("float"))
      raise ValueError(f"{src}: info.json features need the action {action_key!r} (--action_key "
                       f"names another; float features: {vectors}) and at least one camera "
                       f"(dtype video or image); found {sorted(features)}")
    self.fps = float(self.info["fps"])
    self.episodes = self._episodes()
    self._rows = self._read_rows()

  def _episodes(self) -> dict[int, dict]:
    """episode index -> its metadata row (``tasks``, ``length``, v3 video offsets)."""
    import pyarrow.parquet as pq
    if self.version == "v2":
      path = os.path.join(self.src, "meta", "episodes.jsonl")
      with open(path) as f:
        rows = [json.loads(line) for line in f if line.strip()]
    else:
      files = sorted(glob.glob(os.path.join(self.src, "meta", "episodes", "**", "*.parquet"),
                               recursive=True))
      if not files:
        raise ValueError(f"{self.src}: a v3 dataset needs meta/episodes/**/*.parquet")
      rows = [row for f in files for row in pq.read_table(f).to_pylist()]
    return {int(row["episode_index"]): row for row in rows}

  def _read_rows(self) -> dict[int, list[dict]]:
    """episode index -> its frame rows in ``frame_index`` order."""
    import pyarrow.parquet as pq
    files = sorted(glob.glob(os.path.join(self.src, "data", "**", "*.parquet"), recursive=True))
    if not files:
      raise ValueError(f"{self.src}: no data/**/*.parquet")
    rows: dict[int, list[dict]] = {}
    for path in files:
      for row in pq.read_table(path).to_pylist():
        rows.setdefault(int(row["episode_index"]), []).append(row)
    for episode in rows.values():
      episode.sort(key=lambda r: r["frame_index"])
    return rows

  def splits(self) -> dict[str, list[int]]:
    """Split name -> episode indices (``info.json``'s ``"train": "0:50"``; all episodes in
    ``train`` when it lists none)."""
    listed = self.info.get("splits") or {"train": f"0:{max(self._rows) + 1}"}
    out = {}
    for name, span in listed.items():
      start, stop = (int(v) for v in str(span).split(":"))
      out[name] = [e for e in sorted(self._rows) if start <= e < stop]
    return out

  def _video_path(self, key: str, episode: int) -> tuple[str, int]:
    """The video file of ``key`` holding ``episode`` and the episode's first frame in it."""
    template = self.info["video_path"]
    if self.version == "v2":
      chunk = episode // int(self.info.get("chunks_size", 1000))
      path = template.format(episode_chunk=chunk, video_key=key, episode_index=episode)
      return os.path.join(self.src, path), 0
    meta = self.episodes[episode]
    path = template.format(video_key=key, chunk_index=int(meta[f"videos/{key}/chunk_index"]),
                           file_index=int(meta[f"videos/{key}/file_index"]))
    return (os.path.join(self.src, path),
            int(round(float(meta[f"videos/{key}/from_timestamp"]) * self.fps)))

  def camera_frames(self, key: str, episode: int, streams: dict[str, Any]) -> np.ndarray:
    """uint8 ``[L, H, W, 3]`` of camera ``key`` in ``episode``; ``streams`` holds each camera's
    open :class:`~wmjax.data.videoio.VideoStream` (a v3 file holds several episodes, read on
    from where the last one ended)."""
    rows = self._rows[episode]
    if self.info["features"][key]["dtype"] == "image":
      return np.stack([np.asarray(Image.open(io.BytesIO(r[key]["bytes"])).convert("RGB"))
                       for r in rows])
    from wmjax.data.videoio import VideoStream
    path, first = self._video_path(key, episode)
    if key not in streams or streams[key].path != path:
      if not os.path.isfile(path):
        raise ValueError(f"{self.src}: episode {episode} has no video {path}")
      if key in streams:
        streams[key].close()
      streams[key] = VideoStream(path)
    return streams[key].read(first, len(rows))

  def instruction(self, episode: int) -> str:
    tasks = self.episodes.get(episode, {}).get("tasks") or []
    return "; ".join(str(t) for t in tasks)

  def steps(self, episode: int, camera: str, streams: dict) -> list[dict[str, Any]]:
    """The RLDS steps of ``episode`` (see the module doc)."""
    rows = self._rows[episode]
    cameras = {"image" if key == camera else camera_name(key):
               self.camera_frames(key, episode, streams) for key in self.cameras}
    vectors = ({"state": np.asarray([r["observation.state"] for r in rows], np.float32)}
               if "observation.state" in rows[0] else {})
    actions = np.asarray([r[self.action_key] for r in rows], np.float32).reshape(len(rows), -1)
    return episode_steps(cameras, actions, self.instruction(episode), vectors)


def _step_features(dataset: LeRobotDataset, camera: str) -> dict[str, Any]:
  features = dataset.info["features"]

  def size(key):
    return int(np.prod([int(v) for v in features[key]["shape"]]))

  def image_shape(key):
    dims = [int(v) for v in features[key]["shape"]]  # [H, W, C] ("names": height, width, ...)
    if list(features[key].get("names") or [])[:1] == ["channels"]:
      dims = dims[1:] + dims[:1]
    return dims[0], dims[1]

  vectors = {"state": size("observation.state")} if "observation.state" in features else {}
  return step_features({"image" if k == camera else camera_name(k): image_shape(k)
                        for k in dataset.cameras}, size(dataset.action_key), vectors)


def _examples(dataset: LeRobotDataset, camera: str, episodes: list[int]):
  """The split's (key, episode) pairs; each camera's video stream stays open across episodes."""
  streams: dict[str, Any] = {}
  try:
    for episode in episodes:
      yield episode, {"steps": dataset.steps(episode, camera, streams),
                      "episode_metadata": {"episode_id": episode}}
  finally:
    for stream in streams.values():
      stream.close()


def import_lerobot(src: str, out: str, camera: str | None = None,
                   action_key: str = "action") -> str:
  """Write the LeRobot dataset ``src`` as an ArrayRecord RLDS builder directory ``out`` (must not
  exist; written beside it first and renamed when complete); ``camera``: the feature key stored
  as ``observation/image`` (default the first camera); ``action_key``: the feature stored as the
  action. Returns ``out``."""
  out = check_out(out)
  dataset = LeRobotDataset(src, action_key)
  camera = camera or dataset.cameras[0]
  if camera not in dataset.cameras:
    raise ValueError(f"{src} has no camera {camera!r}; cameras: {dataset.cameras}")
  splits = {name: functools.partial(_examples, dataset, camera, episodes)
            for name, episodes in dataset.splits().items()}
  return write_builder(out, "lerobot", f"LeRobot dataset {dataset.src} imported by wmjax",
                       _step_features(dataset, camera), splits,
                       dict(source=os.path.abspath(dataset.src), camera=camera,
                            action=dataset.action_key, fps=dataset.fps))
