"""Push-T (gym-pusht): the simulator, its frame geometry and scripted policies
(:mod:`.simulator`), the dataset (:mod:`.dataset`), the agent and T metrics read from frames
(:mod:`.metrics`), the ``coverage`` reward (:mod:`.rewards`) and the ``push`` control task
(:mod:`.control`), registered as a task
(``config.task = "wmjax.tasks.pusht"``). :mod:`.evaluate` (policy evaluation and planning against
the simulator) sits on the evaluation layer and is imported by the command line, not from here."""

from wmjax import registry
from wmjax.tasks.pusht import control, dataset, metrics, rewards

registry.register(registry.Task(
    __name__, datasets={"pusht": registry.GeneratedDataset(dataset.PushTConfig, dataset.prepare)},
    frame_metrics={"pusht": metrics.FRAME_METRICS}, rewards={"coverage": rewards.coverage},
    control_tasks={"push": control.PushTask.from_config}))
