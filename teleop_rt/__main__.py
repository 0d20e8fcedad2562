"""``python -m teleop_rt``: the same command line as ``teleop-rt``."""

import sys

from teleop_rt.cli import main

if __name__ == "__main__":
    sys.exit(main())
