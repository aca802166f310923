"""`python -m closedloop.cli ...`: the `closedloop` command."""

import sys

from closedloop.cli.main import main

sys.exit(main())
