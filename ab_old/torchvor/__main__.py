"""``python -m torchvor``: see :mod:`torchvor.cli`."""
import sys

from .cli import main

if __name__ == "__main__":
    sys.exit(main())
