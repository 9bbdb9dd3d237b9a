"""``python -m warpfem ...``: the ``warpfem`` command line (see :mod:`warpfem.cli`)."""

import sys

from warpfem.cli import main

sys.exit(main())
