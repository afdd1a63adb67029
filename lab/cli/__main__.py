"""``python -m lab.cli``: run a study from a clone of the repository."""

import sys

from lab.cli.main import main

sys.exit(main())
