"""Teacher-forced denoising error against noise level, on held-out windows.

For a trained workdir: the first ``rollout.context`` frames of each held-out window are shown
clean (at ``sampling.context_level``, as in a rollout), every later frame is noised to one level
with the same noise for every model, and the network's x0 estimate of the later frames is
compared with the truth (MSE in [-1, 1] pixels, and the square IoU of the estimate). One row
per level; a model that denoises well at every level but rolls out badly has a sampler problem,
one that fails at the high levels cannot place the squares from the context and the actions.

    python experiments/gridworld/denoising_error.py WORKDIR [--windows 64] [--out F.json]
"""

from __future__ import annotations

import argparse
import json
import sys

import jax
import jax.numpy as jnp
import numpy as np

from wmjax.diffusion import GaussianDiffusion
from wmjax.model import load_model
from wmjax.tasks.gridworld import dataset as gridworld
from wmjax.tasks.gridworld import metrics as gridworld_metrics
from wmjax.train.data import build_data, eval_windows


def denoising_errors(workdir: str, windows: int = 64, fractions=(0.0, 0.1, 0.25, 0.5, 0.75, 0.9,
                                                                   1.0)) -> list[dict]:
  model = load_model(workdir)
  config = model.config
  config.train.eval_windows = windows
  batch = eval_windows(build_data(config), config)
  frames = jnp.asarray(batch["frames"])  # [B, T, H, W, C] in [-1, 1]
  actions = jnp.asarray(batch["actions"])
  action_mask = jnp.asarray(batch.get("action_mask", np.ones(actions.shape[:2], bool)))
  b, t = frames.shape[:2]
  c = config.rollout.context
  process = model.world_model.process
  context_level = process.level(config.sampling.context_level)
  noise = jax.random.normal(jax.random.key(0), frames.shape)
  colors = gridworld.COLORS[:config.data.gridworld.num_squares]
  discrete = isinstance(process, GaussianDiffusion)  # integer levels in [0, T-1]
  rows = []
  for fraction in fractions:
    level = int(round(fraction * (process.num_timesteps - 1))) if discrete else float(fraction)
    levels = jnp.concatenate([jnp.full((b, c), context_level, jnp.float32),
                              jnp.full((b, t - c), level, jnp.float32)], axis=1)
    if discrete:
      levels = levels.astype(jnp.int32)
    noisy = process.add_noise(frames, levels, noise)
    noisy = noisy.at[:, :c].set(process.context_input(frames[:, :c], context_level))
    out = model.world_model.denoise(model.params, noisy, levels, actions, action_mask)
    x0, _ = process.to_x0_eps(noisy, levels, out)
    x0 = jnp.clip(x0[:, c:], -1.0, 1.0)
    truth = frames[:, c:]
    iou, _ = gridworld_metrics.square_iou(np.asarray(x0), np.asarray(truth), colors)
    rows.append({"fraction": fraction, "level": float(level),
                 "x0_mse": float(jnp.mean((x0 - truth) ** 2)),
                 "square_iou": float(iou.mean())})
  return rows


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("workdir")
  parser.add_argument("--windows", type=int, default=64)
  parser.add_argument("--out", default=None)
  args = parser.parse_args(argv)
  rows = denoising_errors(args.workdir, args.windows)
  print("| level | x0 MSE | x0 square IoU |\n|---|---|---|")
  for r in rows:
    print(f"| {r['level']:g} | {r['x0_mse']:.4f} | {r['square_iou']:.3f} |")
  if args.out:
    with open(args.out, "w") as f:
      json.dump(rows, f, indent=1)
  return 0


if __name__ == "__main__":
  sys.exit(main())
