"""``python -m wmjax.cli``: the ``wmjax`` command (used by ``wmjax launch`` for its processes)."""

import sys

from wmjax.cli import main

sys.exit(main())
