import sys

from tembayes.cli import main

sys.exit(main())
