"""`python -m mocap ARGS`: the command line, as the `mocap` entry point runs it."""

import sys

from mocap.cli import main

sys.exit(main())
