"""Publish a finished temporary file under its final name at most once.

A task re-run after its worker died (or run twice by a scheduler that lost
track of it) must not write its result a second time. ``os.link`` fails when
the final name exists, so the first finished copy wins, whole, and a later
one is discarded; readers never see a half-written file (the temporary name
is hidden: ``.NAME.…``). On a filesystem without hard links (some FUSE mounts of object stores) the
file is renamed into place instead: still whole, but two racing writers may both publish (the same
content, for the deterministic tasks here).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Callable


def publish_once(final: str | os.PathLike, write: Callable[[Path], None], suffix: str | None = None) -> bool:
    """Call ``write(tmp)`` on a temporary file beside ``final``, then link it to ``final`` if that is still free.

    Returns True when this call published ``final``, False when it already existed (then ``write`` is
    not called at all if it existed beforehand; a lost race discards this copy). ``suffix`` is the
    temporary file's extension (libraries such as numpy look at it; default: ``final``'s).
    """
    final = Path(final)
    if final.exists():
        return False
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{final.name}.", suffix=final.suffix if suffix is None else suffix,
                                dir=final.parent)
    os.close(fd)
    tmp = Path(name)
    try:
        write(tmp)
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(tmp, 0o666 & ~mask)  # mkstemp creates 0600; give the file the usual mode
        try:
            os.link(tmp, final)
        except FileExistsError:
            return False
        except OSError:  # no hard links here (EPERM, ENOTSUP…): an atomic rename, unless already published
            if final.exists():
                return False
            os.replace(tmp, final)
        return True
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
