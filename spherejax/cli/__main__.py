"""`python -m spherejax.cli ...`: the command line, as the `spherejax` script runs it."""

import sys

from .run import main

if __name__ == "__main__":
    sys.exit(main())
