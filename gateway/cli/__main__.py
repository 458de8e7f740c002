"""``python -m busgate.gateway.cli``: the ``busgate`` command."""

import sys

from busgate.gateway.cli import main

sys.exit(main())
