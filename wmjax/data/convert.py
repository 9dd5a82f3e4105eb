"""Rewrite a TFRecord RLDS dataset (a TFDS builder directory) as ArrayRecord, without beam or TF.

The records are the same serialized examples in another container, so conversion copies bytes:
each ``*.tfrecord-00000-of-00016`` shard becomes ``*.array_record-00000-of-00016`` with the same
examples in the same order, and ``dataset_info.json`` is updated to the new file format. The
output is written to a temporary directory and renamed into place when complete, so a failure
never leaves a half-converted dataset; an existing output is never overwritten. A shard that
cannot hold the episodes ``dataset_info.json`` counts (missing, empty) stops it before anything
is written.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import struct
from typing import Iterator

from etils import epath
from tensorflow_datasets.core import file_adapters

from wmjax.data.sources import check_shards, open_builder


def tfrecord_records(path: epath.PathLike) -> Iterator[bytes]:
  """The records of a TFRecord file (length-prefixed frames; CRCs are skipped, not checked)."""
  with epath.Path(path).open("rb") as f:
    while header := f.read(12):
      if len(header) != 12:
        raise ValueError(f"{path}: truncated TFRecord header")
      (length,) = struct.unpack("<Q", header[:8])
      data = f.read(length)
      if len(data) != length or len(f.read(4)) != 4:
        raise ValueError(f"{path}: truncated TFRecord record")
      yield data


def convert_to_array_record(src: epath.PathLike, dst: epath.PathLike) -> epath.Path:
  """Convert the TFRecord builder directory ``src`` into ``dst``; returns ``dst``."""
  src, dst = epath.Path(src), epath.Path(dst)
  info_path = src / "dataset_info.json"
  if not info_path.exists():
    raise ValueError(f"{src} is not a TFDS dataset directory (no dataset_info.json)")
  info = json.loads(info_path.read_text())
  file_format = info.get("fileFormat", "tfrecord")
  if file_format != "tfrecord":
    raise ValueError(f"{src} is stored as {file_format}, not tfrecord")
  if dst.exists():
    raise ValueError(f"{dst} already exists; refusing to overwrite it")
  shards = sorted(p for p in src.iterdir() if ".tfrecord-" in p.name)
  if not shards:
    raise ValueError(f"{src} holds no *.tfrecord-* shards")
  check_shards(open_builder(src), src)

  tmp = dst.parent / f".{dst.name}.incomplete"
  if tmp.exists():
    shutil.rmtree(tmp)
  made = [p for p in (dst.parent, *dst.parent.parents) if not p.exists()]  # innermost first
  tmp.mkdir(parents=True)
  try:
    for path in src.iterdir():
      if ".tfrecord-" not in path.name and path.is_file():
        path.copy(tmp / path.name)
    for shard in shards:
      out = tmp / shard.name.replace(".tfrecord-", ".array_record-")
      file_adapters.ArrayRecordFileAdapter.write_examples(
          out, ((None, record) for record in tfrecord_records(shard)))
    info["fileFormat"] = "array_record"
    (tmp / "dataset_info.json").write_text(json.dumps(info, indent=2))
    tmp.rename(dst)
  except BaseException:
    shutil.rmtree(tmp, ignore_errors=True)
    for parent in made:  # the directories made for dst: a failure leaves nothing behind
      with contextlib.suppress(OSError):
        parent.rmdir()
    raise
  return dst
