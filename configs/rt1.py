"""IRASim's training recipe for RT-1 (Open-X ``fractal20220817_data``): IRASim-XL/2 Frame-Ada
on SDXL VAE latents, 16-frame windows, linear schedule with eps prediction, AdamW 1e-4, clip 0.1,
EMA 0.9999, batch 64 (see ``configs/irasim.py``; ``get_config('S')`` etc. for other sizes,
``get_config('tiny')`` to try it without downloaded weights: a random tiny VAE and model).

  wmjax data convert gs://gresearch/robotics/fractal20220817_data/0.1.0 /data/rt1
  wmjax train --config configs/rt1.py --workdir /ckpt/rt1 \\
      --config.data.builder_dir=/data/rt1 --config.codec.path=/models/sdxl-vae
  wmjax train --config configs/rt1.py:tiny --workdir /tmp/rt1-tiny \\
      --config.data.builder_dir=/data/rt1     # a smoke run without VAE weights
"""

import os

from wmjax.config import load_config


def get_config(size: str = "XL"):  # an IRASim size or 'tiny'
  return load_config(os.path.join(os.path.dirname(os.path.abspath(__file__)), "irasim.py")
                     + f":{size},rt1")
