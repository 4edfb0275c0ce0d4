"""Reading the SDK's JSON files (metadata, sidecars, captures, calibrations): an object or a clear error.

Every reader wants the same two refusals, each naming the file: text that is not JSON, and JSON of
another shape (a list where an object belongs). The caller picks the exception class its users
already handle (``CalibrationError``, ``RawFileError``, ``ValueError``).
"""

from __future__ import annotations

import json
from pathlib import Path


def read_json_object(path: str | Path, error: type[Exception] = ValueError, what: str = "") -> dict:
    """The JSON object in ``path``; ``error`` naming ``what`` (default: the path) for bad JSON or another shape.

    A missing file raises ``FileNotFoundError`` as usual.
    """
    label = what or str(path)
    try:
        doc = json.loads(Path(path).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise error(f"{label}: not JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise error(f"{label}: holds a JSON {type(doc).__name__}, expected an object")
    return doc
