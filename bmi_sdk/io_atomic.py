"""Atomic file writes: write to a temporary name in the same folder, then rename.

A crash or Ctrl-C never leaves a half-written file under the final name.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None, replace: bool = True) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` on success.

    ``suffix`` keeps the extension libraries look at (e.g. ``.png`` for OpenCV,
    ``.npz`` for numpy); by default the final path's suffix is used.
    ``replace`` False: a file already at ``path`` (or one another process put there meanwhile) is kept and
    ``FileExistsError`` raised; the new file is linked into place, which fails rather than replaces.
    """
    final = Path(path)
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(
        prefix=f".{final.name}.", suffix=final.suffix if suffix is None else suffix, dir=final.parent
    )
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; give the file the usual mode
        if replace:
            os.replace(tmp, final)
        else:
            os.link(tmp, final)  # FileExistsError when something is there: never replaced
            tmp.unlink()
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def write_bytes(path: str | os.PathLike, data: bytes, replace: bool = True) -> None:
    with atomic_path(path, replace=replace) as tmp:
        tmp.write_bytes(data)


def write_json(path: str | os.PathLike, obj: Any, replace: bool = True) -> None:
    write_bytes(path, (json.dumps(obj, indent=2, sort_keys=False) + "\n").encode(), replace)


def save_npy(path: str | os.PathLike, array: np.ndarray) -> None:
    with atomic_path(path, suffix=".npy") as tmp:
        np.save(tmp, array, allow_pickle=False)


class FolderBusyError(FileExistsError):
    """Another running process holds the folder's lock (``lock_folder``): it is writing there."""


def lock_folder(path: Path, error: type[FolderBusyError] = FolderBusyError) -> int:
    """An open descriptor of ``path`` (a lock file in the folder one run at a time writes) holding its exclusive
    ``flock``, with this process's id written in it; ``error`` (naming the holder) when another process holds it.
    The kernel drops the lock of a process that dies, so a dead run's lock is taken over.

    Taken on the file that is at ``path`` when the lock is granted: a holder unlinks the file as it lets go, so a
    lock won on a file unlinked in between is dropped and tried again on the new one."""
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise error(f"{path.parent} is being written by another run (process {holder}); "
                        "wait for it to finish, or choose another folder") from None
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(path))
        except FileNotFoundError:
            same = False
        if same:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
            return fd
        os.close(fd)


def unlock_folder(path: Path, fd: int) -> None:
    """Let go of ``lock_folder``'s lock on ``path`` (its descriptor ``fd``) and remove the lock file."""
    with contextlib.suppress(FileNotFoundError):
        path.unlink()  # while still holding the lock: a waiting run then locks a new file, never this one
    os.close(fd)


@contextlib.contextmanager
def locked_folder(path: Path, error: type[FolderBusyError] = FolderBusyError) -> Iterator[None]:
    """Hold ``lock_folder(path)`` for the block (its folder created first), then let go."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = lock_folder(path, error)
    try:
        yield
    finally:
        unlock_folder(path, fd)
