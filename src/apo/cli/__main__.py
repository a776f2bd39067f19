"""``python -m apo.cli``."""

import sys

from apo.cli import main

sys.exit(main())
