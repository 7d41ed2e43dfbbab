"""`python -m jaxrefl.cli`: the `jaxrefl` command."""

import sys

from . import main

sys.exit(main())
