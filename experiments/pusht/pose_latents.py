"""Screen: pre-encoded Push-T latents whose actions also carry the state each frame shows.

Copies a ``wmjax data encode`` folder, appending to each step's action ``a_t`` the six numbers
:func:`wmjax.tasks.pusht.perception.perceived_state` reads off that step's frame (the
simulator's render, as the dataset stores it): action ``t`` then says where the agent is sent
*and* where the agent and the T are when it is sent. The action statistics are recomputed over
the train split, so the model standardises the appended numbers as it does the actions.

    python experiments/pusht/pose_latents.py SRC_LATENTS DST_LATENTS [next]

With ``next``, each action also carries the state of the frame it leads to (the last step's
own again): an oracle of the pose dynamics, for a renderer screen.
"""

from __future__ import annotations

import json
import os
import shutil
import sys

import jax.numpy as jnp
import numpy as np
from array_record.python.array_record_module import ArrayRecordWriter
from flax import serialization

from wmjax.data import oxe
from wmjax.data.latents import METADATA, LatentEpisodes, _split_file, read_metadata
from wmjax.data.rlds import make_window
from wmjax.data.sources import ArrayRecordEpisodes
from wmjax.data.stats import ActionStats
from wmjax.frames import to_model
from wmjax.tasks.pusht.perception import perceived_state


def main(src: str, dst: str, mode: str = "now") -> None:
  if mode not in ("now", "next"):
    raise ValueError(mode)
  if os.path.exists(dst):
    raise FileExistsError(dst)
  meta = read_metadata(src)
  spec = oxe.DatasetSpec.from_dict(meta["spec"])
  tmp = dst + ".incomplete"
  shutil.rmtree(tmp, ignore_errors=True)
  os.makedirs(tmp)
  train_actions = []
  for split in meta["splits"]:
    latents = LatentEpisodes(src, split)
    pixels = ArrayRecordEpisodes(meta["builder_dir"], split, spec)
    indexes = np.flatnonzero(pixels.lengths())
    assert len(indexes) == len(latents), (split, len(indexes), len(latents))
    writer = ArrayRecordWriter(os.path.join(tmp, _split_file(split)), "group_size:1")
    for record_index, index in enumerate(indexes):
      record = serialization.msgpack_restore(latents._source[record_index])
      episode = pixels.episode(int(index))
      np.testing.assert_array_equal(episode.actions.astype(np.float32), record["actions"])
      window = make_window(episode, 0, len(episode), tuple(meta["resolution"]), int(index),
                           spec.resize)
      state = np.asarray(perceived_state(to_model(jnp.asarray(window["frames"]), xp=jnp)))
      parts = [record["actions"], state]
      if mode == "next":
        parts.append(np.concatenate([state[1:], state[-1:]]))
      record["actions"] = np.concatenate(parts, -1).astype(np.float32)
      writer.write(serialization.msgpack_serialize(record))
      if split == "train":
        train_actions.append(record["actions"][:-1])
    writer.close()
  stats = ActionStats.compute(np.concatenate(train_actions), meta["dataset"], None)
  meta["action_stats"] = stats.to_dict()
  meta["spec"]["action_dim"] = stats.action_dim
  with open(os.path.join(tmp, METADATA), "w") as f:
    json.dump(meta, f, indent=2)
  os.rename(tmp, dst)
  print(json.dumps(meta["action_stats"], indent=1))


if __name__ == "__main__":
  main(*sys.argv[1:])
