"""Tasks: the simulators wmjax generates data from and what is particular to each (dataset
builder, policies, metrics, rewards, evaluation). A task module registers a
:class:`wmjax.registry.Task` when it is imported; a config names the module it uses
(``config.task``), and completing the config imports it (:func:`wmjax.config.import_task`).

* :mod:`wmjax.tasks.gridworld` — WPE's gridworld of coloured squares;
* :mod:`wmjax.tasks.pusht` — Push-T (gym-pusht).
"""
