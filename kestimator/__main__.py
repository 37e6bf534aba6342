"""`python -m kestimator`: the same as the `kestimator` command."""

import sys

from kestimator.entry import kestimator

sys.exit(kestimator())
