"""What a report records about the software and the input that made it: versions, execution provider, input path.

A result can then be traced to the SDK and onnxruntime that made it and the frame it came from.
Versions are read from the installed distributions' metadata, so recording them loads nothing.
"""

from __future__ import annotations

import os
import platform
from importlib import metadata

import bmi_sdk


def _installed_version(distribution: str) -> str | None:
    try:
        return metadata.version(distribution)
    except metadata.PackageNotFoundError:
        return None


def software_versions() -> dict:
    """{"bmi_sdk", "onnxruntime", "python"}: the versions in use (``onnxruntime`` None where not installed)."""
    return {"bmi_sdk": bmi_sdk.__version__, "onnxruntime": _installed_version("onnxruntime"),
            "python": platform.python_version()}


def input_path_of(frame_or_path) -> str | None:
    """The absolute path of a frame given by path; None for a ``RawFrame`` given in memory."""
    if isinstance(frame_or_path, (str, os.PathLike)):
        return os.path.abspath(os.fspath(frame_or_path))
    return None


def provenance(input_path: str | None, execution_provider: str | None) -> dict:
    """The report's provenance fields; ``execution_provider`` None for a decoder without an onnxruntime session."""
    return {"software": software_versions(), "execution_provider": execution_provider, "input_path": input_path}
