"""The model file on disk: read (bounded, checked) and written (atomically); the schema
and its checks are core/model/model_doc.py's, shared with the model message."""

from __future__ import annotations

import yaml

from piezo_stage.core.model.duhem import StageModel
from piezo_stage.core.model.model_doc import (  # noqa: F401 - the file's names, as before
    SCHEMA_KEY,
    as_number,
    checked_doc,
    model_from_dict,
    model_to_dict,
    parse_yaml,
)
from piezo_stage.core.types import Doc
from piezo_stage.io.files import atomic_write, load_yaml  # noqa: F401 - (as before)


def load_model(path) -> tuple[StageModel, Doc]:
    """Read a model file; returns (StageModel, effects)."""
    return model_from_dict(load_yaml(path, "model file"), str(path))


def save_model(path, model: StageModel, effects=None, extra=None) -> list[str]:
    """Write the model file atomically, checked as the loader checks it first
    (``model_doc.checked_doc``: a law bounded past its fitted range where it must be,
    ModelError and nothing written where it is no stage). -> the notes of what was
    bounded."""
    doc, notes = checked_doc(model, effects, extra)
    save_document(path, doc)
    return notes


def save_document(path, doc: Doc) -> None:
    """Write a model document built by ``checked_doc`` (``save_model``'s, or a
    diagnosis's ``document()``) atomically, as it is: what its writer scored is what a
    reader loads (YAML keeps every float exactly)."""
    with atomic_write(path) as fh:
        yaml.safe_dump(doc, fh, sort_keys=False, default_flow_style=None)
