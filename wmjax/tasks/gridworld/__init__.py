"""WPE's gridworld (appendix C.1): the dataset (:mod:`.dataset`), the square metrics
(:mod:`.metrics`), the true environment (:mod:`.env`) and the ``reach`` control task
(:mod:`.reach`), registered as a task (``config.task = "wmjax.tasks.gridworld"``)."""

from wmjax import registry
from wmjax.tasks.gridworld import dataset, metrics, reach

registry.register(registry.Task(
    __name__, datasets={"gridworld": registry.GeneratedDataset(dataset.GridworldConfig,
                                                               dataset.prepare)},
    frame_metrics={"gridworld": metrics.FRAME_METRICS},
    control_tasks={"reach": reach.ReachTask.from_config}))
