"""Push-T: where the imagined T's pixels go, frame by frame of closed-loop rollouts.

The T's IoU against the simulator (``wmjax.tasks.pusht.metrics``) falls with every generated
frame, even when nothing touches the T. This splits that loss: for each generated frame, the
simulator's T pixels that the model does not show as T, counted by the class the model shows
there instead (every pixel is classed by its nearest palette colour,
:func:`wmjax.tasks.pusht.simulator.classify_pixels`), the pixels the model adds, both T's pixel
counts, and the mean colour the model paints on the T's outline (its pixels next to a non-T pixel)
and inside it, against the simulator's. A T that fades at its edges loses outline pixels to the
lighter classes while its count and interior stay; a T that moves wrongly or melts into a blob
loses pixels to the background and adds as many elsewhere. It also gives the codec's own IoU
(the simulator's frames encoded and decoded).

Episodes start from the held-out ``evaluate`` stream (as ``wmjax eval-policy`` does) and run
through the same closed-loop scan:

    python experiments/pusht/lost_pixels.py --workdir W/model --step 3000 --policy stay \\
        --policy push --episodes 16 --out lost_pixels.json
"""

from __future__ import annotations

import argparse
import json

import jax
import numpy as np

from wmjax.frames import to_model, to_uint8
from wmjax.model import load_model
from wmjax.tasks.pusht import evaluate, simulator


def _classes(frames) -> np.ndarray:
  return np.asarray(simulator.classify_pixels(to_model(np.asarray(frames))))


def _outline(mask: np.ndarray) -> np.ndarray:
  """The pixels of ``mask [..., H, W]`` with a 4-neighbour outside it."""
  inner = mask.copy()
  inner[..., 1:, :] &= mask[..., :-1, :]
  inner[..., :-1, :] &= mask[..., 1:, :]
  inner[..., :, 1:] &= mask[..., :, :-1]
  inner[..., :, :-1] &= mask[..., :, 1:]
  return mask & ~inner


def frame_report(truth: np.ndarray, imagined: np.ndarray) -> dict:
  """One generated frame: ``truth`` and ``imagined`` uint8 ``[B, H, W, 3]``."""
  true_class, model_class = _classes(truth), _classes(imagined)
  true_t, model_t = true_class == simulator.BLOCK, model_class == simulator.BLOCK
  lost, added = true_t & ~model_t, model_t & ~true_t
  outline = _outline(true_t)
  names = simulator.PALETTE_NAMES
  return {
      "block_iou": float((true_t & model_t).sum() / max((true_t | model_t).sum(), 1)),
      "true_pixels": int(true_t.sum()), "model_pixels": int(model_t.sum()),
      "lost_as": {names[k]: int((model_class[lost] == k).sum()) for k in range(len(names))},
      "added_over": {names[k]: int((true_class[added] == k).sum()) for k in range(len(names))},
      "outline_rgb": {"model": imagined[outline].mean(0).round(1).tolist(),
                      "simulator": truth[outline].mean(0).round(1).tolist()},
      "interior_rgb": {"model": imagined[true_t & ~outline].mean(0).round(1).tolist(),
                       "simulator": truth[true_t & ~outline].mean(0).round(1).tolist()},
  }


def policy_report(model, spec: str, episodes: int, steps: int, seed: int) -> dict:
  """Every generated frame's :func:`frame_report` for policy ``spec`` over ``episodes``."""
  config = model.config
  c = config.rollout.context
  policy = simulator.policy_from_spec(spec, evaluate.policy_chunk(config))
  states = evaluate.initial_states(config, episodes, "evaluate", seed)
  truth, imagined = evaluate.simulate_and_imagine(model, policy, states, steps,
                                                  jax.random.key(seed), jax.random.key(seed + 1),
                                                  scan=True)
  imagined = np.asarray(to_uint8(imagined))
  frames = [frame_report(truth["frames"][:, t], imagined[:, t])
            for t in range(c, imagined.shape[1])]
  decoded = model.codec.decode(model.codec.encode(to_model(truth["frames"][:, c:])))
  codec = frame_report(truth["frames"][:, c:], np.asarray(to_uint8(decoded)))
  return {"held_out": evaluate.held_out(config, states), "frames": frames,
          "codec_round_trip": codec}


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--workdir", required=True)
  parser.add_argument("--step", type=int, default=None)
  parser.add_argument("--policy", action="append", default=None,
                      help="push | push:NOISE | stay (repeatable; default stay and push)")
  parser.add_argument("--episodes", type=int, default=16)
  parser.add_argument("--steps", type=int, default=8, help="actions per episode")
  parser.add_argument("--seed", type=int, default=0)
  parser.add_argument("--out", default=None, help="JSON with every number")
  args = parser.parse_args(argv)
  model = load_model(args.workdir, step=args.step)
  report = {spec: policy_report(model, spec, args.episodes, args.steps, args.seed)
            for spec in args.policy or ("stay", "push")}
  for spec, result in report.items():
    print(f"## {spec} (held out: {result['held_out']}; codec round trip IoU "
          f"{result['codec_round_trip']['block_iou']:.3f})")
    print("| frame | IoU | T pixels (simulator / model) | lost as background / goal / wall | "
          "outline RGB (model / simulator) |")
    print("|---|---|---|---|---|")
    for i, f in enumerate(result["frames"], 1):
      lost = f["lost_as"]
      print(f"| {i} | {f['block_iou']:.3f} | {f['true_pixels']} / {f['model_pixels']} | "
            f"{lost['background']} / {lost['goal']} / {lost['wall']} | "
            f"{f['outline_rgb']['model']} / {f['outline_rgb']['simulator']} |")
  if args.out:
    with open(args.out, "w") as f:
      json.dump(report, f, indent=1)


if __name__ == "__main__":
  main()
