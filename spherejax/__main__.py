"""`python -m spherejax ...`: the command line, as the `spherejax` script runs it."""

import sys

from .cli import main

if __name__ == "__main__":
    sys.exit(main())
