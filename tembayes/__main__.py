"""Entry point for ``python -m tembayes``: runs the command-line interface."""

import sys

from tembayes.cli import main

sys.exit(main())
