"""Which of JAX's platforms a process may start: no TPU client on a machine without TPU chips."""

import os


def skip_absent_tpu() -> bool:
  """Leave the TPU out of JAX's platform search on a machine without TPU chips, unless
  ``JAX_PLATFORMS`` or ``JAX_FORCE_TPU_INIT`` asks for it; whether it was left out.

  Called when ``wmjax`` is imported, so that no process using wmjax (the ``wmjax`` command, an
  experiment script, a notebook, research code) starts a TPU client where there is no TPU. With
  ``libtpu`` installed (the ``tpu`` extra brings it, to compile for TPU topologies on any
  machine) JAX tries to start a TPU client on every machine, and libtpu then prints lines of
  ``INVALID_ARGUMENT`` errors about worker hostnames on a CPU or GPU host. Compiling for a TPU
  topology (``wmjax compile --target v5p:2x2x1``) loads libtpu by itself and is not affected.
  The platform stays known (TPU lowering rules still register); its factory reports no chips,
  as JAX's own search does for CUDA without a visible GPU. The chip count and the factory
  registry are JAX internals: if they move, nothing is left out.
  """
  if os.environ.get("JAX_PLATFORMS") or os.environ.get("JAX_FORCE_TPU_INIT"):
    return False
  try:
    from jax._src import hardware_utils, xla_bridge
    if hardware_utils.num_available_tpu_chips_and_device_id()[0] > 0:
      return False
    registration = xla_bridge._backend_factories["tpu"]
    xla_bridge.register_backend_factory("tpu", _no_tpu_chips, priority=registration.priority,
                                        fail_quietly=True)
    return True
  except (ImportError, AttributeError, KeyError, RuntimeError):
    return False


def _no_tpu_chips():
  raise RuntimeError("this machine has no TPU chips")
