"""``python -m workbench``: the same as the ``workbench`` command."""

import sys

from workbench.cli import main

if __name__ == "__main__":  # Dask's worker processes start by spawn, which imports this module again
    sys.exit(main())
