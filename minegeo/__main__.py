import sys

from minegeo.cli import main

sys.exit(main())
