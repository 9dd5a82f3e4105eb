"""Frames/s of the grain input path (ArrayRecord read + image decode + resize + windowing +
normalisation + batching) with 0, 1 and 2 worker processes, at 64x64 and 256x320; writes JSON.

  python benchmarks/data_pipeline.py [--batches 40] [--out benchmarks/results/data_pipeline.json]

The data is the synthetic gridworld rendered at 128x128 (resized to 64x64) and at 256x256
(resized to 256x320), 16-frame windows, stride 1, batch 8.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time

from wmjax.data.pipeline import WindowSource, training_pipeline
from wmjax.data.sources import ArrayRecordEpisodes, action_stats
from wmjax.tasks.gridworld import dataset as gridworld

CASES = {"64x64": (128, (64, 64)), "256x320": (256, (256, 320))}


def measure(builder_dir: str, resolution, workers: int, batches: int, batch_size: int,
            frames: int) -> float:
  source = WindowSource(ArrayRecordEpisodes(builder_dir, "train"), frames, 1, resolution)
  ds = training_pipeline([source], [action_stats(builder_dir)], batch_size=batch_size,
                         num_workers=workers, shard_index=0, shard_count=1)
  it = iter(ds)
  for _ in range(3):  # warm-up: worker start-up and first reads
    next(it)
  start = time.perf_counter()
  for _ in range(batches):
    next(it)
  return batches * batch_size * frames / (time.perf_counter() - start)


def main():
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--batches", type=int, default=40)
  parser.add_argument("--batch_size", type=int, default=8)
  parser.add_argument("--frames", type=int, default=16)
  parser.add_argument("--data_dir", default=os.path.join(tempfile.gettempdir(), "wmjax_bench"))
  parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results",
                                                    "data_pipeline-cpu.json"))
  args = parser.parse_args()
  results = {"cpu_cores": os.cpu_count(), "batch_size": args.batch_size, "frames": args.frames,
             "frames_per_s": {}}
  for name, (native, resolution) in CASES.items():
    builder_dir = gridworld.prepare(args.data_dir, gridworld.GridworldConfig(
        image_size=native, square_size=native // 5, max_speed=native / 10, train_episodes=64,
        test_episodes=1))
    for workers in (0, 1, 2):
      rate = measure(builder_dir, resolution, workers, args.batches, args.batch_size, args.frames)
      results["frames_per_s"][f"{name}/workers={workers}"] = rate
      print(f"{name} workers={workers}: {rate:.0f} frames/s", flush=True)
  os.makedirs(os.path.dirname(args.out), exist_ok=True)
  with open(args.out, "w") as f:
    json.dump(results, f, indent=2)
  print(f"wrote {args.out}")


if __name__ == "__main__":
  main()
