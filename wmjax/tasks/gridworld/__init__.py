"""WPE's gridworld (appendix C.1): the dataset (:mod:`.dataset`) and the square metrics
(:mod:`.metrics`), registered as a task (``config.task = "wmjax.tasks.gridworld"``)."""

from wmjax import registry
from wmjax.tasks.gridworld import dataset, metrics

registry.register(registry.Task(
    __name__, datasets={"gridworld": registry.GeneratedDataset(dataset.GridworldConfig,
                                                               dataset.prepare)},
    frame_metrics={"gridworld": metrics.FRAME_METRICS}))
