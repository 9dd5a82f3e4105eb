"""The world model for inference: :class:`WorldModel` (network, diffusion process and sampler)
and :func:`load_model`, which reads what inference needs from a training checkpoint (parameters,
config, action statistics, codec) into a :class:`LoadedModel`.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from typing import Any, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import orbax.checkpoint as ocp

from wmjax.codecs import Codec, make_codec
from wmjax.config import apply_overrides
from wmjax.data.stats import ActionStats
from wmjax.diffusion import objectives
from wmjax.diffusion.sampling import (DenoiseFn, SamplerConfig, classifier_free_guidance,
                                      context_inputs, window_denoiser)
from wmjax.errors import CheckpointError, describe_error, ignore_closed_loop_callbacks
from wmjax.nn import float8
from wmjax.nn.dit import STDiT, relayout_layers
from wmjax.parallel import abstract_with_shardings, local_data_mesh

Params = Any


@functools.partial(jax.jit, static_argnums=(0, 2))
def _init_network(network: STDiT, rng: jax.Array, shape: tuple[int, ...]) -> Params:
  """``network.init`` on zero frames ``shape = [1, T, H, W, C]``: compiled once per network and
  shape (equal networks share it), not traced again at every :meth:`WorldModel.init`."""
  x = jnp.zeros(shape, jnp.float32)
  actions = jnp.zeros(shape[:1] + (shape[1] - 1, network.action_dim), jnp.float32)
  return network.init(rng, x, jnp.zeros(shape[:2], jnp.float32), actions)


@dataclasses.dataclass(frozen=True, eq=False)
class WorldModel:
  """The network, its diffusion process and how it is sampled; hashable by identity (jit-static)."""

  network: STDiT
  process: objectives.Process
  sampler: SamplerConfig

  def __post_init__(self):
    if self.sampler.kv_cache and not self.network.causal_temporal:
      raise ValueError("sampling.kv_cache=True needs model.causal_temporal=True: with "
                       "bidirectional temporal attention the context frames attend to the new "
                       "frames, so their keys and values change at every sampling step")

  @classmethod
  def from_config(cls, config: ml_collections.ConfigDict) -> "WorldModel":
    """From a config with ``model`` (STDiT fields), ``diffusion`` and ``sampling`` sections."""
    d = config.diffusion
    process = objectives.make_process(d.kind, d.schedule, d.num_timesteps, d.prediction)
    sampler = SamplerConfig(**config.sampling.to_dict())
    if sampler.sampler not in process.samplers:
      raise ValueError(f"sampling.sampler={sampler.sampler!r} does not fit diffusion.kind="
                       f"{d.kind!r}; expected one of {process.samplers}")
    return cls(STDiT(**config.model.to_dict()), process, sampler)

  def init(self, rng: jax.Array, frame_shape: tuple[int, int, int], frames: int | None = None
           ) -> Params:
    """Initial variables for frames of ``frame_shape = (H, W, C)``, compiled as one program (run
    eagerly, every initialiser and layer would be an XLA program of its own).

    The leaves are Flax boxes (``flax.linen.LogicallyPartitioned``: the array and its logical
    axis names, which the sharding rules of :mod:`wmjax.parallel` map to a mesh). The model's
    methods take them as they are; ``flax.linen.unbox(variables)`` gives the plain arrays that
    :func:`load_model` returns and that an optax optimiser or a checkpoint wants."""
    n = frames or self.network.num_frames
    return _init_network(self.network, rng, (1, n) + tuple(frame_shape))

  # Classifier-free guidance runs the network on the batch twice, conditional then null.

  @property
  def guided(self) -> bool:
    return self.sampler.guidance_scale != 1.0

  def _twice(self, x: jax.Array) -> jax.Array:
    return jnp.concatenate([x, x], axis=0) if self.guided else x

  def _conditioning(self, actions: jax.Array, action_mask: jax.Array):
    """``(actions, action_mask, drop_actions)`` of the network's batch."""
    if not self.guided:
      return actions, action_mask, None
    b = actions.shape[0]
    drop = jnp.concatenate([jnp.zeros((b,), bool), jnp.ones((b,), bool)])
    return self._twice(actions), self._twice(action_mask), drop

  def _guide(self, out: jax.Array) -> jax.Array:
    if not self.guided:
      return out
    b = out.shape[0] // 2
    return classifier_free_guidance(out[:b], out[b:], self.sampler.guidance_scale)

  def denoise(self, params: Params, x: jax.Array, levels: jax.Array, actions: jax.Array,
              action_mask: jax.Array) -> jax.Array:
    """Network output for the window ``x [B, T, ...]`` at process levels ``[B, T]``, with guidance."""
    t = self.process.model_time(levels)
    out = self.network.apply(params, self._twice(x), self._twice(t),
                             *self._conditioning(actions, action_mask))
    return self._guide(out)

  def calibrate_float8(self, params: Params, windows: jax.Array, actions: jax.Array,
                       rng: jax.Array, context: int = 1) -> Params:
    """``params`` with the scales that make a ``model.fp8_matmuls`` network's float8 matmuls
    static (:mod:`wmjax.nn.float8`): every float8 layer's largest input magnitude while the
    network denoises the clean ``windows [B, T, ...]`` (its own frames: latents for a latent
    model) under their ``actions [B, T-1, A]``, the first ``context`` frames clean as the sampler
    gives them, the others noised to each level the sampler visits. Windows from the training
    data are what a model's rollouts resemble; a larger input in a rollout is clipped to
    ``float8.HEADROOM`` times the calibrated maximum."""
    if not self.network.fp8_matmuls:
      raise ValueError("calibrate_float8 needs a network with model.fp8_matmuls=True")
    b, n = windows.shape[:2]
    if actions.shape[:2] != (b, n - 1) or not 0 < context < n:
      raise ValueError(f"calibration wants windows [B, T, ...], actions [B, T-1, A] and "
                       f"0 < context < T; got windows {tuple(windows.shape)}, actions "
                       f"{tuple(actions.shape)}, context {context}")
    context_in, context_levels = context_inputs(self.process, self.sampler, windows[:, :context])
    conditioning = self._conditioning(actions, jnp.ones(actions.shape[:2], bool))
    weights = {k: v for k, v in params.items() if k != float8.COLLECTION}

    @jax.jit
    def record(seen, level, noise):
      new = windows[:, context:]
      levels = jnp.full(new.shape[:2], level, context_levels.dtype)
      x = jnp.concatenate([context_in, self.process.add_noise(new, levels, noise)], axis=1)
      t = self.process.model_time(jnp.concatenate([context_levels, levels], axis=1))
      _, updated = self.network.apply({**weights, **seen}, self._twice(x), self._twice(t),
                                      *conditioning, mutable=[float8.COLLECTION])
      return updated

    seen = {}
    for level, key in zip(self.process.sampling_levels(self.sampler.num_steps)[1:],
                          jax.random.split(rng, self.sampler.num_steps)):
      seen = record(seen, level, jax.random.normal(key, windows[:, context:].shape))
    return {**weights, **seen}

  def new_frame_denoiser(self, params: Params, context: jax.Array, actions: jax.Array,
                         action_mask: jax.Array) -> DenoiseFn:
    """What the sampler calls at every step: ``(x [B, h, ...], levels [B, h]) -> out`` for the
    ``h`` frames after the clean ``context [B, c, ...]``, under the window's ``actions
    [B, c+h-1, A]`` and ``action_mask [B, c+h-1]``. With ``sampler.kv_cache`` the context goes
    through the network once, here; otherwise every step runs the whole window."""
    context_in, context_levels = context_inputs(self.process, self.sampler, context)
    if not self.sampler.kv_cache:
      return window_denoiser(lambda x, levels: self.denoise(params, x, levels, actions, action_mask),
                             context_in, context_levels, self.sampler.context_shares_level)
    conditioning = self._conditioning(actions, action_mask)
    cache = self.network.apply(params, self._twice(context_in),
                               self._twice(self.process.model_time(context_levels)), *conditioning,
                               method="encode_context")

    def denoise(x, levels):
      out = self.network.apply(params, cache, self._twice(x),
                               self._twice(self.process.model_time(levels)), *conditioning,
                               method="extend")
      return self._guide(out)

    return denoise


@dataclasses.dataclass(frozen=True)
class LoadedModel:
  """A trained world model ready for rollouts, read from a training workdir."""

  config: ml_collections.ConfigDict
  world_model: WorldModel
  params: Any  # EMA or raw parameters, replicated over the local devices
  action_stats: ActionStats
  step: int
  codec: Codec  # RGB frames <-> the model's space (config.codec)

  @property
  def frame_shape(self) -> tuple[int, int, int]:
    """The model's frames (latents for a VAE codec)."""
    return tuple(self.config.frame_shape)

  @property
  def image_shape(self) -> tuple[int, int, int]:
    """The RGB frames the codec takes."""
    return self.codec.image_shape(self.frame_shape)

  def normalize_actions(self, actions: Any) -> np.ndarray:
    """Raw actions ``[..., A]`` -> what the network takes: normalised by the checkpoint's
    statistics as it trained (``data.normalization``), zero-padded to ``model.action_dim``."""
    return self.action_stats.normalize(actions, mode=self.config.data.normalization,
                                       pad_to=self.config.model.action_dim)


def load_model(workdir: str, *, step: int | None = None, params: str = "ema",
               overrides: Sequence[str] = (), param_dtype: str = "float32") -> LoadedModel:
  """The parameters (``params='ema'`` or ``'raw'``), config and action statistics of a training
  checkpoint in ``workdir`` (the latest, or ``step``); nothing else of the train state is read.
  ``overrides`` (``dotted.key=value``) change inference settings such as ``sampling.num_steps``,
  ``model.dtype``, ``model.fp8_matmuls`` or ``model.scan_layers`` (the saved layers are stacked
  or unstacked to match, :func:`wmjax.nn.dit.relayout_layers`); ``param_dtype='bfloat16'``
  halves the parameters' memory for inference."""
  if params not in ("ema", "raw"):
    raise ValueError(f"params must be 'ema' or 'raw', got {params!r}")
  directory = os.path.join(os.path.abspath(os.path.expanduser(workdir)), "checkpoints")
  if not os.path.isdir(directory):
    raise FileNotFoundError(f"{workdir} holds no checkpoints/ directory; train a model there "
                            f"first (wmjax train --workdir {workdir})")
  ignore_closed_loop_callbacks()
  manager = ocp.CheckpointManager(directory, options=ocp.CheckpointManagerOptions(create=False))
  try:
    steps = sorted(manager.all_steps())
    if not steps:
      raise FileNotFoundError(f"{directory} holds no complete checkpoint")
    if step is None:
      step = steps[-1]
    elif step not in steps:
      raise ValueError(f"no checkpoint for step {step} in {directory}; steps: {steps}")

    def read(item, args):
      try:
        return manager.restore(step, args=ocp.args.Composite(**args))
      except Exception as e:
        others = [s for s in steps if s != step]
        hint = (f"; the other checkpoints are steps {others}: pass --step {others[-1]} (or "
                f"step={others[-1]}) to use one" if others else "")
        raise CheckpointError(f"checkpoint {step} cannot be read: "
                              f"{os.path.join(directory, str(step), item)}: "
                              f"{describe_error(e)}{hint}") from e

    config = ml_collections.ConfigDict(read("config", dict(config=ocp.args.JsonRestore())).config)
    stats = read("action_stats", dict(action_stats=ocp.args.JsonRestore())).action_stats
    # the layout the layers were saved in; model.scan_layers=... may ask for the other
    saved_scan = bool(config.get("model", {}).get("scan_layers", STDiT.scan_layers))
    # A checkpoint written before a config key existed gets its default (the schema in
    # wmjax.config), which an override may then change (e.g. sampling.kv_cache).
    config = apply_overrides(config, overrides, strict=False)
    world_model = WorldModel.from_config(config)
    frame_shape = tuple(config.frame_shape)
    abstract = nn.unbox(jax.eval_shape(
        lambda: world_model.init(jax.random.key(0), frame_shape,
                                 min(config.data.frames, config.model.num_frames))))
    replicated = jax.sharding.NamedSharding(local_data_mesh(), jax.sharding.PartitionSpec())
    key = "ema_params" if params == "ema" else "params"
    target = {key: relayout_layers(abstract_with_shardings(
        abstract, jax.tree.map(lambda _: replicated, abstract)), saved_scan)}
    restored = read("state", dict(state=ocp.args.PyTreeRestore(
        target, partial_restore=True,
        restore_args=ocp.checkpoint_utils.construct_restore_args(target))))
  finally:
    manager.close()
  weights = jax.tree.map(lambda p: p.astype(param_dtype),
                         relayout_layers(restored.state[key], config.model.scan_layers))
  return LoadedModel(config, world_model, weights,
                     ActionStats.from_dict(stats), int(step),
                     make_codec(config.codec))
