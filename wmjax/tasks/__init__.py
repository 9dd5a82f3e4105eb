"""Tasks: the simulators wmjax generates data from and what is particular to each (dataset
builder, policies, metrics, rewards, evaluation). Each registers with the generic code on import
(:mod:`wmjax.registry`, :func:`wmjax.data.sources.register_generated`,
:func:`wmjax.data.oxe.register`); importing this package registers them all.

* :mod:`wmjax.tasks.gridworld` — WPE's gridworld of coloured squares;
* :mod:`wmjax.tasks.pusht` — Push-T (gym-pusht).
"""

from wmjax.tasks import gridworld, pusht  # noqa: F401  (they register on import)
