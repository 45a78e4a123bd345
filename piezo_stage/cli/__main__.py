"""``python -m piezo_stage.cli``: the ``piezo-stage`` command (``python -m piezo_stage``
also takes stop signals during the command's imports)."""

import sys

from piezo_stage import stopping
from piezo_stage.cli import main

code = main()
stopping.hold()  # as piezo_stage.__main__: a stop after the end is ignored
sys.exit(code)
