"""``python -m bridge ARGS``: the same as the ``scmbridge`` command."""

import sys

from bridge.tools.cli import main

sys.exit(main())
