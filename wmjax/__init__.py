"""wmjax: action-conditioned video world models for robot manipulation in JAX."""

__version__ = "0.1.0"
