"""``python -m twinrl.cli``: the ``twinrl`` command."""

import sys

from twinrl.cli import main

sys.exit(main())
