"""`python -m cosim`: the cosim command line."""

import sys

from .cli import main

sys.exit(main())
