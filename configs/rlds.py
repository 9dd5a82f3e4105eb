"""A small pixel-space world model for any RLDS dataset: yours, an Open-X one, or a LeRobot
dataset brought in by ``wmjax data import lerobot`` — the reading is all in ``config.data``.

``data.spec`` (schema: :class:`wmjax.data.oxe.DatasetSpec`) says where the camera(s),
instruction and action are; left with empty ``action_keys`` the built-in spec of
``data.dataset`` is used (``lerobot``, the Open-X names, gridworld, pusht). ``data.image_key``
picks a camera (several: tiled views), ``data.resize`` crop or pad. ``wmjax data inspect DIR``
prints a dataset's features and a suggested spec. ``model.action_dim`` must be the spec's action
dimension and ``frame_shape`` the resolution (pixel codec).

  wmjax train --config configs/rlds.py --workdir /tmp/run --config.data.builder_dir=DIR \\
      --config.data.dataset=lerobot --config.model.action_dim=6
"""

import ml_collections

from wmjax.config import load_config
from wmjax.data.oxe import spec_config

RESOLUTION = (64, 64)


def get_config() -> ml_collections.ConfigDict:
  import os
  # the gridworld's recipe: 2-frame windows (a clean frame, the next one noised), 1-frame blocks
  config = load_config(os.path.join(os.path.dirname(os.path.abspath(__file__)), "gridworld.py"))
  config.name = "rlds"
  config.task = ""  # a dataset of your own: no generated one
  config.frame_shape = RESOLUTION + (3,)
  config.data = ml_collections.ConfigDict(dict(
      dataset="lerobot", builder_dir="", spec=spec_config(action_keys=()), image_key="",
      resize="crop", missing_image="skip", frame_step=1, resolution=RESOLUTION, frames=2,
      train_stride=1, eval_stride=6, normalization="mean_std", num_workers=0,
      train_split="train[:90%]", eval_split="train[90%:]"))
  config.model.patch_size = 4
  return config
