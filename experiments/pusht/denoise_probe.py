"""Push-T: does the model put the agent back from one noisy frame, by noise level?

For the 3-frame windows (stride 1, the first 64) of today's data's ``test`` split: the first two
frames clean, the third noised to each level, one call of the network, its x0 prediction of the
third frame scored by the agent's centroid error (px of the model's frame; a missing agent counts
24 px) and how often an agent is drawn at all. A model that draws the agent only where the noisy
input still carries it, and not from high noise, has not learnt where the action and the context
put it.

    python experiments/pusht/denoise_probe.py --workdir W/model --data_dir D --step 1000 \\
        --out W/denoise.json
"""

from __future__ import annotations

import argparse
import functools
import json

import numpy as np

LEVELS = (50, 200, 400, 600, 800, 999)
MISSING_PX = 24.0


def denoise_probe(workdir: str, step: int, data_dir: str, windows: int = 64) -> dict:
  import jax
  import jax.numpy as jnp

  from wmjax.data.sources import ArrayRecordEpisodes
  from wmjax.eval.trajectories import Trajectories, windows_of
  from wmjax.frames import to_model
  from wmjax.model import load_model
  from wmjax.tasks.pusht import dataset as pusht_data
  from wmjax.tasks.pusht import simulator

  model = load_model(workdir, step=step)
  params = dict(model.config.data.pusht)
  params.pop("mix", None)  # the reference data: all scripted, as probe.py's
  params.pop("random_reach", None)
  episodes = ArrayRecordEpisodes(
      pusht_data.prepare(data_dir, pusht_data.PushTConfig.from_dict(params)), "test", "pusht")
  normalize = functools.partial(model.action_stats.normalize, mode=model.config.data.normalization,
                                pad_to=model.config.model.action_dim)
  size = tuple(model.config.frame_shape[:2])
  batch = Trajectories.stack(windows_of(episodes, 3, size, windows), normalize)
  frames, actions = jnp.asarray(to_model(batch.frames)), jnp.asarray(batch.actions)[:, :2]
  truth = simulator.centroids(frames[:, 2])[1]
  wm = model.world_model
  apply = jax.jit(wm.network.apply)
  rows = {}
  for level in LEVELS:
    levels = jnp.broadcast_to(jnp.asarray([-1, -1, level]), (len(frames), 3))
    noise = jax.random.normal(jax.random.key(level), frames[:, 2].shape)
    noisy = frames.at[:, 2].set(wm.process.add_noise(frames[:, 2], levels[:, 2], noise))
    out = apply(model.params, noisy, wm.process.model_time(levels), actions)[:, 2]
    drawn = np.asarray(simulator.object_masks(out)[1].any((-2, -1)))
    error = np.linalg.norm(np.asarray(simulator.centroids(out)[1] - truth), axis=-1)
    error = np.where(drawn, error * size[0] / simulator.WORKSPACE, MISSING_PX)
    rows[str(level)] = {"agent_error_px": float(error.mean()),
                        "agent_error_px_stderr": float(error.std(ddof=1) / np.sqrt(len(error))),
                        "agent_drawn": float(drawn.mean())}
  return {"workdir": workdir, "step": int(model.step), "windows": int(len(frames)), "levels": rows}


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                   formatter_class=argparse.RawDescriptionHelpFormatter,
                                   epilog="\n".join(__doc__.splitlines()[1:]))
  parser.add_argument("--workdir", required=True, help="the model's workdir (checkpoints/)")
  parser.add_argument("--data_dir", required=True,
                      help="TFDS data directory holding (or to hold) the reference dataset")
  parser.add_argument("--step", type=int, required=True)
  parser.add_argument("--out", required=True, help="JSON file")
  args = parser.parse_args(argv)
  result = denoise_probe(args.workdir, args.step, args.data_dir)
  for level, row in result["levels"].items():
    print(f"level {level}: agent error {row['agent_error_px']:.1f} ± "
          f"{row['agent_error_px_stderr']:.1f} px, drawn in {row['agent_drawn']:.0%}")
  with open(args.out, "w") as f:
    json.dump(result, f, indent=2)
  return 0


if __name__ == "__main__":
  raise SystemExit(main())
