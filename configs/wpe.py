"""WPE's training recipe: the 609M-parameter world model (``configs/wpe_600m.py``: per-frame
noise levels, sigmoid schedule, v prediction, causal temporal attention) on SD3 VAE latents of
256x256 frames (32x32x16), trained on a weighted mixture of RT-1, Bridge and Language-Table
(Open-X; Language-Table's 2-dim actions are zero-padded to 7). Each dataset is normalised with its
own action statistics. WPE does not give its mixture weights; these are equal (override
``data.mixture.<name>.weight``).

  wmjax data convert gs://gresearch/robotics/fractal20220817_data/0.1.0 /data/rt1   # and the others
  wmjax train --config configs/wpe.py --workdir /ckpt/wpe \\
      --config.data.mixture.fractal20220817_data.builder_dir=/data/rt1 \\
      --config.data.mixture.bridge.builder_dir=/data/bridge \\
      --config.data.mixture.language_table.builder_dir=/data/language_table \\
      --config.codec.path=/models/sd3-vae

``get_config('tiny')`` (``configs/wpe.py:tiny``) tries the recipe without downloaded weights: a
random SD3-layout VAE and a tiny model on small frames (:func:`wmjax.config.tiny_profile`).
"""

import os

import ml_collections

from wmjax.codecs import codec_config
from wmjax.config import load_config, tiny_profile

HERE = os.path.dirname(os.path.abspath(__file__))
# (Open-X name, published location, held-out split)
MIXTURE = (
    ("fractal20220817_data", "gs://gresearch/robotics/fractal20220817_data/0.1.0", "train[95%:]"),
    ("bridge", "gs://gresearch/robotics/bridge/0.1.0", "test"),
    ("language_table", "gs://gresearch/robotics/language_table/0.0.1", "train[95%:]"),
)


PROFILES = ("", "tiny")


def get_config(profile: str = "") -> ml_collections.ConfigDict:
  if profile not in PROFILES:
    raise ValueError(f"WPE recipe profile must be one of {PROFILES}, got {profile!r}")
  config = load_config(os.path.join(HERE, "wpe_600m.py"))
  config.name = "wpe-600m-openx"
  # The SD3 VAE as a diffusers folder (the vae/ of stabilityai/stable-diffusion-3-medium-diffusers):
  # 16 channels, scaling 1.5305, shift 0.0609 (read from its config.json).
  config.codec = codec_config(kind="vae", path="~/models/sd3-vae", dtype="bfloat16")
  config.frame_shape = (32, 32, 16)
  config.data = ml_collections.ConfigDict(dict(
      dataset=MIXTURE[0][0], resolution=(256, 256), frames=20, train_stride=1, eval_stride=20,
      normalization="mean_std", num_workers=8, train_split="train", eval_split="test"))
  config.data.mixture = ml_collections.ConfigDict({
      name: dict(builder_dir=location, latents_dir="", weight=1.0,
                 train_split="train" if held_out == "test" else "train[:95%]",
                 eval_split=held_out)
      for name, location, held_out in MIXTURE})
  config.train = ml_collections.ConfigDict(dict(
      num_steps=300_000, log_every=100, checkpoint_every=5_000, eval_every=5_000,
      eval_windows=16, max_checkpoints=3,
      # fit before the first step: compiled memory against the device's limit (or the budget)
      auto_fit=True, memory_budget_gib=None))
  return tiny_profile(config, "sd3", "wpe-tiny-openx") if profile == "tiny" else config
