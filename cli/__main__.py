"""``python -m posefuse.cli ...``: the ``posefuse`` command."""

import sys

from posefuse.cli.main import main

sys.exit(main())
