"""``python -m skyfix`` runs the command line."""

import sys

from skyfix.cli import main

sys.exit(main())
