"""`python -m orchestrator.cli` runs the `calfit` command line."""

import sys

from . import main

sys.exit(main())
