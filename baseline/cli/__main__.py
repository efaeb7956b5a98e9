"""``python -m baseline.cli``: the same as ``pgs``."""
import sys

from baseline.cli import main

sys.exit(main())
