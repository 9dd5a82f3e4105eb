"""IRASim's training recipe for Bridge (Open-X ``bridge``): IRASim-XL/2 Frame-Ada
on SDXL VAE latents, 16-frame windows, linear schedule with eps prediction, AdamW 1e-4, clip 0.1,
EMA 0.9999, batch 64 (see ``configs/irasim.py``; ``get_config('S')`` etc. for other sizes,
``get_config('tiny')`` to try it without downloaded weights: a random tiny VAE and model).

  wmjax data convert gs://gresearch/robotics/bridge/0.1.0 /data/bridge
  wmjax train --config configs/bridge.py --workdir /ckpt/bridge \\
      --config.data.builder_dir=/data/bridge --config.codec.path=/models/sdxl-vae
  wmjax train --config configs/bridge.py:tiny --workdir /tmp/bridge-tiny \\
      --config.data.builder_dir=/data/bridge     # a smoke run without VAE weights
"""

import os

from wmjax.config import load_config


def get_config(size: str = "XL"):  # an IRASim size or 'tiny'
  return load_config(os.path.join(os.path.dirname(os.path.abspath(__file__)), "irasim.py")
                     + f":{size},bridge")
