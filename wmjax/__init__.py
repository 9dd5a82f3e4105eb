"""wmjax: action-conditioned video world models for robot manipulation in JAX."""

__version__ = "0.1.0"

from wmjax.platforms import skip_absent_tpu

skip_absent_tpu()  # libtpu installed on a CPU or GPU machine: no TPU client, no libtpu noise
