"""``python -m cli ...``: the ``posefuse`` command."""

import sys

from cli.main import main

sys.exit(main())
