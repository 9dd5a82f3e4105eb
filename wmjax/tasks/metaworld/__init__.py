"""MetaWorld (a Sawyer arm with a gripper, seen by several cameras): the simulator wrapper, its
scripted, random and idle agents (:mod:`.simulator`), the dataset (:mod:`.dataset`), per-view frame
metrics (:mod:`.metrics`) and the frame reader of the arm's state and the task's success
(:mod:`.reader`), registered as a task (``config.task = "wmjax.tasks.metaworld"``).
:mod:`.evaluate` (policy evaluation against the simulator) sits on the evaluation layer and is
imported by its callers, not from here. Nothing here imports MetaWorld until it simulates: without
the ``metaworld`` extra the task registers, and writing data says which extra to install."""

from wmjax import registry
from wmjax.tasks.metaworld import dataset, metrics

registry.register(registry.Task(
    __name__, datasets={"metaworld": registry.GeneratedDataset(dataset.MetaWorldConfig,
                                                               dataset.prepare)},
    frame_metrics={"metaworld": metrics.FRAME_METRICS}))
