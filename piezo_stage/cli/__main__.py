"""``python -m piezo_stage.cli``: the ``piezo-stage`` command."""

import sys

from piezo_stage.cli import main

sys.exit(main())
