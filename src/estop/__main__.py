"""``python -m estop``: the ``estop`` command line."""

import sys

from estop.cli import main

sys.exit(main())
