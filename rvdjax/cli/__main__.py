import sys

from rvdjax.cli import main

sys.exit(main())
