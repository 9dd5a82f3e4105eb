"""Why a training run stopped, for conditions the message explains with the way out."""


class RunError(RuntimeError):
  """A training run cannot go on, for a reason its message states with the way out; the command
  line prints the message alone, without a traceback."""
