"""``python -m voxe_core.cli``: the ``voxe`` command."""

import sys

from voxe_core.cli import main

sys.exit(main())
