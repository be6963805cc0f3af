"""``python -m minegeo.cli``: the same as the ``minegeo`` console script."""

import sys

from minegeo.cli import main

sys.exit(main())
