"""``python -m services.cli ARGS``: the `fp` command (tests run the nodes this way)."""

import sys

from services.cli import main

sys.exit(main())
