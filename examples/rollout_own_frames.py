"""Roll a trained world model out from your own frames and raw actions, and save the video.

  python examples/rollout_own_frames.py WORKDIR --frames frames.npy --actions actions.npy \\
      --out rollout.gif

``frames.npy``: uint8 ``[B, c, H, W, 3]``, the first ``c`` frames of each episode (``c``: the
model's ``rollout.context``); ``actions.npy``: raw actions ``[B, N, A]`` as the dataset records
them, action ``k`` leading from frame ``c-1+k`` to frame ``c+k``. ``rollout`` takes normalised
actions, so they go through the checkpoint's statistics first.
"""

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from wmjax.eval.video import frame_grid, write_png, write_video
from wmjax.frames import to_model, to_uint8
from wmjax.model import load_model
from wmjax.rollout import rollout


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("workdir")
  parser.add_argument("--frames", required=True)
  parser.add_argument("--actions", required=True)
  parser.add_argument("--out", default="rollout.gif", help=".gif or .mp4 (episode 0); a .png grid "
                                                           "of every episode beside it")
  parser.add_argument("--seed", type=int, default=0)
  args = parser.parse_args(argv)

  model = load_model(args.workdir)                    # EMA parameters, config, statistics, codec
  config = model.config
  frames, raw = np.load(args.frames), np.load(args.actions)
  c = config.rollout.context
  actions = model.action_stats.normalize(raw, config.data.normalization,
                                         pad_to=config.model.action_dim)
  context = model.codec.encode(jnp.asarray(to_model(frames[:, :c])))
  latents = rollout(model.world_model, model.params, context, jnp.asarray(actions),
                    jax.random.key(args.seed), horizon=config.rollout.horizon)
  video = to_uint8(model.codec.decode(latents))       # [B, c + N, H, W, 3]
  write_video(args.out, video[0])
  write_png(args.out.rsplit(".", 1)[0] + ".png", frame_grid(video))
  print(f"{video.shape[0]} episodes of {video.shape[1]} frames -> {args.out}")
  return video


if __name__ == "__main__":
  main()
