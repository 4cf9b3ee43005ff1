"""``python -m ringscan``: the ``ringscan`` command."""

import sys

from ringscan.tools.cli import main

if __name__ == "__main__":
    sys.exit(main())
