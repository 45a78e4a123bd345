"""``python -m piezo_stage.cli``: the ``piezo-stage`` command (``python -m piezo_stage``
also takes stop signals during the command's imports)."""

import sys

from piezo_stage.cli import main

sys.exit(main())
