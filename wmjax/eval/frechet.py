"""Fréchet distances (FID over frames, FVD over clips) from user-supplied feature networks."""

from __future__ import annotations

from typing import Callable

import jax
import numpy as np

from wmjax.eval import metrics
from wmjax.frames import to_unit


FeatureFn = Callable[[jax.Array], jax.Array]


class FrechetDistances:
  """FID over frames and FVD over clips from user-supplied feature networks:
  ``frame_features([N, H, W, 3] in [0, 1]) -> [N, D]`` and ``clip_features([N, T, H, W, 3] in
  [0, 1]) -> [N, D]`` (e.g. a Flax InceptionV3 / I3D ``apply`` closed over its weights). Used on
  equal-length clips (IRASim computes them for short trajectories only)."""

  def __init__(self, frame_features: FeatureFn | None, clip_features: FeatureFn | None):
    self.functions = {"fid": frame_features, "fvd": clip_features}
    self.moments = {name: (metrics.FeatureMoments(), metrics.FeatureMoments())
                    for name, fn in self.functions.items() if fn is not None}

  def update(self, truth: np.ndarray, predicted: np.ndarray) -> None:
    """``truth``, ``predicted``: uint8 clips ``[N, T, H, W, 3]``."""
    for name, (real, fake) in self.moments.items():
      for moments, clips in ((real, truth), (fake, predicted)):
        x = to_unit(clips)
        if name == "fid":
          x = x.reshape((-1,) + x.shape[2:])
        moments.update(np.asarray(self.functions[name](x)).reshape(len(x), -1))

  def result(self) -> dict[str, float]:
    return {name: metrics.frechet_distance(real, fake)
            for name, (real, fake) in self.moments.items()}
