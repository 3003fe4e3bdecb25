"""``python -m bridge ARGS``: the same as the ``scmbridge`` command."""

import sys

from bridge.core.lifeline import hold

hold()  # a child of the demo or a bench goes away with its parent (bridge/core/lifeline.py)

from bridge.tools.cli import main  # noqa: E402

sys.exit(main())
