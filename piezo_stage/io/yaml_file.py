"""A YAML file read whole and bounded (core/yaml_text.py's parser): a missing,
unreadable or non-UTF-8 file is a ModelError naming what it was meant to be."""

from __future__ import annotations

from piezo_stage.core.errors import ModelError
from piezo_stage.core.yaml_text import MAX_YAML_BYTES, parse_yaml


def load_yaml(path, what="file"):
    """The document in ``path`` (``what`` names it in errors: "config file", ...)."""
    try:
        with open(path, "rb") as fh:
            raw = fh.read(MAX_YAML_BYTES + 1)
    except FileNotFoundError:
        raise ModelError(f"{what} not found: {path}") from None
    except IsADirectoryError:
        raise ModelError(f"{what} is a directory: {path}") from None
    except PermissionError:
        raise ModelError(f"{what} not readable: {path}") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise ModelError(f"{what} is not UTF-8 text: {path}") from None
    return parse_yaml(text, f"{what} {path}")
