"""``python -m u2sa_hw.cli`` is the ``u2sa`` command."""

import sys

from u2sa_hw.cli import main

sys.exit(main())
