"""Push-T (gym-pusht): the simulator, its frame geometry and scripted policies
(:mod:`.simulator`), the dataset (:mod:`.dataset`), the agent and T metrics read from frames
(:mod:`.metrics`) and the ``coverage`` reward (:mod:`.rewards`), registered with the generic
code. :mod:`.evaluate` (policy evaluation and planning against the
simulator) sits on the evaluation layer and is imported by the command line, not from here."""

from wmjax.data.sources import register_generated
from wmjax import registry
from wmjax.tasks.pusht import dataset, metrics, rewards

register_generated("pusht", dataset.PushTConfig, dataset.prepare)
registry.register_reward("coverage", rewards.coverage)
registry.register_frame_metrics("pusht", metrics.FRAME_METRICS)
