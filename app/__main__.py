"""``python -m app`` is the ``cwrr`` command."""

import sys

from app.cli import main

sys.exit(main())
