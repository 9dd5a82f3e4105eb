"""WPE's gridworld (appendix C.1): the dataset (:mod:`.dataset`) and the square metrics
(:mod:`.metrics`), registered with the generic code."""

from wmjax.data.sources import register_generated
from wmjax import registry
from wmjax.tasks.gridworld import dataset, metrics

register_generated("gridworld", dataset.GridworldConfig, dataset.prepare)
registry.register_frame_metrics("gridworld", metrics.FRAME_METRICS)
