"""One process of a 2-process CPU training run (started by test_train_loop.py): trains through
``wmjax.train.loop.train`` and prints a digest of the parameters this process holds."""

import hashlib
import sys

import jax
import numpy as np


def main():
  port, process_id, workdir, *overrides = sys.argv[1:]
  jax.config.update("jax_cpu_collectives_implementation", "gloo")
  jax.distributed.initialize(f"127.0.0.1:{port}", 2, int(process_id))
  from wmjax.config import load_config
  from wmjax.train.loop import train
  config = load_config("configs/gridworld.py", overrides)
  state, _ = train(config, workdir)
  digest = hashlib.sha1()
  for leaf in jax.tree.leaves(state.params):
    digest.update(np.asarray(leaf.addressable_shards[0].data).tobytes())
  print(f"DIGEST {jax.process_index()} {jax.process_count()} {digest.hexdigest()}", flush=True)


if __name__ == "__main__":
  main()
