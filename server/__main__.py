"""``python -m server``: the same as ``telesplat serve``."""

import sys

from .cli import main

sys.exit(main())
