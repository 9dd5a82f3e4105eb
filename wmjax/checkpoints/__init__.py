"""Checkpoints of other codebases as wmjax workdirs (:mod:`wmjax.checkpoints.irasim`)."""
