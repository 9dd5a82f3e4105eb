"""Shard a world model over a device mesh by the library's logical-axis rules, and run a
batch of rollouts split over the devices.

  python examples/shard_over_mesh.py --config configs/irasim.py:S --mesh 1,-1,1
  XLA_FLAGS=--xla_force_host_platform_device_count=8 python examples/shard_over_mesh.py  # on a CPU

The mesh is ``(data, fsdp, tensor)``: ``1,-1,1`` splits every large parameter over all devices
(FSDP), ``1,1,-1`` splits attention heads and MLP columns (tensor parallel), ``-1,1,1`` keeps
the parameters whole on each device. Each parameter is placed by its logical axis names
(``wmjax.parallel.LOGICAL_RULES``); XLA inserts the communication.
"""

import argparse

import flax.linen as nn
import jax
import jax.numpy as jnp

from wmjax import parallel
from wmjax.config import load_config, split_overrides
from wmjax.model import WorldModel
from wmjax.rollout import rollout


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--config", default="configs/irasim.py:S")
  parser.add_argument("--mesh", default="1,-1,1", help="data,fsdp,tensor (-1: the rest)")
  parser.add_argument("--batch", type=int, default=8)
  args, rest = parser.parse_known_args(argv)
  overrides, unknown = split_overrides(rest)
  if unknown:
    parser.error(f"unrecognized arguments: {' '.join(unknown)}")
  config = load_config(args.config, overrides)
  mesh = parallel.make_mesh([int(v) for v in args.mesh.split(",")])
  wm = WorldModel.from_config(config)

  # shapes only (no memory), then each parameter created directly in its shard
  boxed = jax.eval_shape(lambda: wm.init(jax.random.key(0), config.frame_shape))
  shardings = parallel.logical_shardings(boxed, mesh)
  params = jax.jit(lambda key: nn.unbox(wm.init(key, config.frame_shape)),
                   out_shardings=shardings)(jax.random.key(0))
  kernel = params["params"]["blocks"]["layers"]["spatial"]["mlp"]["fc1"]["kernel"]
  print(f"mesh {dict(mesh.shape)}: an MLP kernel {kernel.shape} is stored as "
        f"{kernel.sharding.shard_shape(kernel.shape)} per device")

  c, h = config.rollout.context, config.rollout.horizon
  batch = jax.device_put(jnp.zeros((args.batch, c) + tuple(config.frame_shape)),
                         parallel.batch_sharding(mesh))
  actions = jnp.zeros((args.batch, h, config.model.action_dim))
  with jax.set_mesh(mesh):
    video = rollout(wm, params, batch, actions, jax.random.key(1), horizon=h)
  print(f"{args.batch} rollouts of {video.shape[1]} frames on {mesh.size} devices")
  return video


if __name__ == "__main__":
  main()
