"""`python -m kestimator`: the same as the `kestimator` command."""

import sys

from kestimator.cli import main

sys.exit(main())
