"""One process of a multi-process CPU training run started by the local launcher
(test_train_loop.py): trains through ``wmjax.train.loop.train`` and prints a digest of the
parameters this process holds.

  distributed_worker.py WORKDIR [OVERRIDE ...] --coordinator_address A --num_processes N
      --process_id I
"""

import argparse
import hashlib

import jax
import numpy as np


def main():
  parser = argparse.ArgumentParser()
  parser.add_argument("workdir")
  parser.add_argument("overrides", nargs="*")
  parser.add_argument("--coordinator_address", required=True)
  parser.add_argument("--num_processes", type=int, required=True)
  parser.add_argument("--process_id", type=int, required=True)
  args = parser.parse_args()
  jax.config.update("jax_cpu_collectives_implementation", "gloo")
  jax.distributed.initialize(args.coordinator_address, args.num_processes, args.process_id)
  from wmjax.config import load_config
  from wmjax.train.loop import train
  config = load_config("configs/gridworld.py", args.overrides)
  state, _ = train(config, args.workdir)
  digest = hashlib.sha1()
  for leaf in jax.tree.leaves(state.params):
    digest.update(np.asarray(leaf.addressable_shards[0].data).tobytes())
  print(f"DIGEST {jax.process_index()} {jax.process_count()} {digest.hexdigest()}", flush=True)


if __name__ == "__main__":
  main()
