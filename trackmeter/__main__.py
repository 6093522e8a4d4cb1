"""``python -m trackmeter``: the ``trackmeter`` command (:mod:`trackmeter.cli.main`)."""

import sys

from trackmeter.cli.main import main

if __name__ == "__main__":
    sys.exit(main())
