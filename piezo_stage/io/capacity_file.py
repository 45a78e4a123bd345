"""The capacity file: a driver that refuses to run for want of capacity leaves its
figures (core/loop/capacity.py) where the launcher said, so ``launch --rate auto`` can
start the set again at the rate the host held."""

from __future__ import annotations

import json
import os

from piezo_stage.core.types import Doc
from piezo_stage.io.files import atomic_write

#: the variable the launcher sets to the file's path for the driver
CAPACITY_FILE_ENV = "PIEZO_STAGE_CAPACITY_FILE"


def write_refusal(figures: Doc | None) -> None:
    """The driver's side: ``figures`` to the launcher's file (written whole, then
    renamed), where a launcher asked for them."""
    path = os.environ.get(CAPACITY_FILE_ENV)
    if path and figures is not None:
        with atomic_write(path) as fh:
            json.dump(figures, fh)


def read_refusal(path: str) -> Doc | None:
    """The launcher's side: the figures a driver left at ``path``, else None."""
    try:
        with open(path) as fh:
            figures = json.load(fh)
    except (OSError, ValueError):
        return None
    return figures if isinstance(figures, dict) else None
