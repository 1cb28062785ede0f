"""`python -m kgnavbench`: the `kgnavbench` command."""

import sys

from .cli import main

sys.exit(main())
