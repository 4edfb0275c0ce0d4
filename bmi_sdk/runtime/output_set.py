"""A run's output files as one set: staged in a hidden folder, moved into place only when all are written.

``bmi infer`` writes eight files (ten with the classical decoder's 1σ) and ``report.json``. Written one by one into
the output folder, a run that fails half-way (disk full, Ctrl-C, a crash)
would leave new files beside an earlier run's, with nothing to tell them apart.
``OutputSet`` writes them into ``OUT/.bmi-infer-XXXX/`` (same file system, so
a rename moves them), then removes the old ``report.json`` and any earlier result this run
does not write (a classical run's ``depth_sigma.npy`` under a network run's set), renames each
file into ``OUT`` and renames ``report.json`` last. So:

* a failure while writing leaves ``OUT`` exactly as it was (a folder the run created is removed);
* ``report.json`` in ``OUT`` marks a complete set from one run (the renames
  take microseconds; a kill between them leaves no report, never a wrong one).

It also refuses, before any work is done, an ``OUT`` that holds an earlier
run's results (unless ``overwrite``) or that cannot be written to.

One run at a time writes into an ``OUT``: a run holds an exclusive lock (``fcntl.flock``) on ``OUT/.bmi-infer.lock``
from before its work until its set is in place, and a second run into the same folder is refused
(``OutputFolderBusyError``, naming the process that holds it) instead of replacing the first one's set. The
kernel drops the lock of a process that dies (SIGKILL, the OOM killer), so a dead run's lock is taken over. A
run that holds the lock also removes the staging folders such runs leave behind (no other run into ``OUT`` can
be writing them) and warns that it did (``LeftoverStagingWarning``).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import warnings
from pathlib import Path

from ..io_atomic import FolderBusyError, lock_folder, unlock_folder
from .outputs import OUTPUT_NAMES, SIGMA_OUTPUT_NAMES

REPORT_NAME = "report.json"
RESULT_NAMES = (*OUTPUT_NAMES, *SIGMA_OUTPUT_NAMES, REPORT_NAME)
"""Every file a run may leave in ``OUT`` (``outputs.write_outputs``' names, whichever decoder ran)."""
STAGING_PREFIX = ".bmi-infer-"
LOCK_NAME = ".bmi-infer.lock"


class OutputFolderBusyError(FolderBusyError):
    """Another running process is writing its outputs into the same folder."""


class LeftoverStagingWarning(UserWarning):
    """Staging folders of an interrupted run (killed before it could clean up) were found and removed."""


class OutputSet:
    """Stage one run's outputs in ``staging``; ``commit`` moves them into ``out_dir``. Use as a context manager."""

    def __init__(self, out_dir: str | os.PathLike, overwrite: bool = False):
        self.out_dir = Path(out_dir)
        self.overwrite = overwrite
        self.staging: Path | None = None
        self._created = False  # this run made out_dir: a run that fails before commit() removes it again
        self._lock_fd: int | None = None
        self.removed_staging: list[str] = []  # staging folders of interrupted runs removed by this one
        if self.out_dir.exists() and not self.out_dir.is_dir():
            raise NotADirectoryError(f"output folder {self.out_dir} is a file")
        self._refuse_earlier()

    def _refuse_earlier(self) -> None:
        earlier = [n for n in RESULT_NAMES if (self.out_dir / n).exists()]
        if earlier and not self.overwrite:
            raise FileExistsError(f"{self.out_dir} holds an earlier run's results ({', '.join(earlier)}); "
                                  "pass --overwrite (overwrite=True) to replace them, or choose another folder")

    def __enter__(self) -> "OutputSet":
        """Lock ``out_dir`` for this run, remove what interrupted runs left there, and create the staging folder
        ``self.staging`` (this is the writability check)."""
        try:
            self._created = not self.out_dir.exists()
            self.out_dir.mkdir(parents=True, exist_ok=True)
            self._lock_fd = lock_folder(self.out_dir / LOCK_NAME, OutputFolderBusyError)
        except OutputFolderBusyError:
            self._release()
            raise
        except OSError as exc:
            self._release()
            raise PermissionError(f"cannot write the outputs into {self.out_dir}: {exc.strerror or exc}") from None
        try:
            self._refuse_earlier()  # again, under the lock: a run may have finished since the first check
            self._remove_leftover_staging()
            self.staging = Path(tempfile.mkdtemp(prefix=STAGING_PREFIX, dir=self.out_dir))
        except OSError as exc:
            self._release()
            if isinstance(exc, FileExistsError):
                raise
            raise PermissionError(f"cannot write the outputs into {self.out_dir}: {exc.strerror or exc}") from None
        return self

    @property
    def folder(self) -> Path:
        """The staging folder this run writes its files into (inside the ``with`` block)."""
        if self.staging is None:
            raise RuntimeError("OutputSet.folder exists inside its with block only")
        return self.staging

    def _remove_leftover_staging(self) -> None:
        """Remove the staging folders of runs killed before they cleaned up (SIGKILL, the OOM killer): with the lock
        held no other run into ``out_dir`` is writing one."""
        for leftover in sorted(self.out_dir.glob(STAGING_PREFIX + "*")):
            if leftover.is_dir():
                shutil.rmtree(leftover)
                self.removed_staging.append(leftover.name)
        if self.removed_staging:
            warnings.warn(f"removed {len(self.removed_staging)} staging folder(s) an interrupted run left in "
                          f"{self.out_dir}: {', '.join(self.removed_staging)}", LeftoverStagingWarning, stacklevel=3)

    def commit(self) -> dict[str, str]:
        """Move every staged file into ``out_dir``, ``report.json`` last; return {name: final path}."""
        assert self.staging is not None, "commit() inside the with block"
        names = sorted(p.name for p in self.staging.iterdir())
        with contextlib.suppress(FileNotFoundError):
            (self.out_dir / REPORT_NAME).unlink()  # the old set is no longer complete from here on
        for stale in set(RESULT_NAMES) - set(names):  # an earlier run's file this run does not write
            with contextlib.suppress(FileNotFoundError):
                (self.out_dir / stale).unlink()
        for name in sorted(names, key=lambda n: n == REPORT_NAME):
            os.replace(self.staging / name, self.out_dir / name)
        self._created = False
        return {name: str(self.out_dir / name) for name in names}

    def __exit__(self, *exc) -> None:
        if self.staging is not None:
            shutil.rmtree(self.staging, ignore_errors=True)
            self.staging = None
        self._release()

    def _release(self) -> None:
        """Let go of the lock and remove an output folder this run created and left empty (failed before commit)."""
        if self._lock_fd is not None:
            unlock_folder(self.out_dir / LOCK_NAME, self._lock_fd)
            self._lock_fd = None
        if self._created:
            with contextlib.suppress(OSError):
                self.out_dir.rmdir()
