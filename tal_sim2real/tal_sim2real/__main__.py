"""``python -m tal_sim2real``: see tal_sim2real.cli."""

import sys

from .cli import main

sys.exit(main())
