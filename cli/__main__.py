"""``python -m adjointsim.cli``: the same as the ``adjointsim`` command."""

import sys

from . import main

sys.exit(main())
