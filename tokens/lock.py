"""One writer per dataset folder: `DatasetLock`, the ``DATASET/.lock`` file `tt generate` holds
(and the ``RUN/.lock`` file `tt train` holds for its run folder).

The writer holds an exclusive `fcntl.flock` on the file, which also holds its host name and
pid for messages. The kernel drops the flock of a process that dies (killed, or a zombie),
so a stale lock is free and exactly one of several runs starting together takes it; a lock
file of another host is never taken over (its run may still be going), and the error says
which file to delete.
"""

from __future__ import annotations

import json
import logging
import os
import socket
from pathlib import Path

from tt.tokens.store import DatasetError

logger = logging.getLogger(__name__)


class DatasetLock:
    """One writer per dataset: an exclusive `fcntl.flock` on ``DATASET/.lock``, which holds
    host and pid of the running `tt generate` (for messages).

    The kernel drops the flock of a process that dies, so a lock left by a killed run is
    free, and taking it over is the flock itself: of several runs starting together exactly
    one gets it, the others are refused. (The old protocol read the stale file, unlinked it
    and created a new one, so two runs could both win.) A lock file naming a live process
    of this host, or any process of another host (where flock may not reach), is refused.
    """

    def __init__(self, path: str | Path, *, what: str = ""):
        """what: what the folder is, for messages ("run folder"); default: nothing said."""
        self.file = Path(path) / ".lock"
        self.what = f"{what} " if what else ""
        self.held = False
        self._fd: int | None = None

    @staticmethod
    def _owner(fd: int) -> dict:
        try:
            os.lseek(fd, 0, os.SEEK_SET)
            other = json.loads(os.read(fd, 4096).decode() or "{}")
            return other if isinstance(other, dict) else {}
        except (OSError, ValueError):
            return {}

    def _refuse(self, fd: int, message: str) -> None:
        os.close(fd)
        raise DatasetError(message)

    def __enter__(self) -> "DatasetLock":
        import fcntl

        me = {"host": socket.gethostname(), "pid": os.getpid()}
        for _ in range(8):
            fd = os.open(self.file, os.O_CREAT | os.O_RDWR, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                other = self._owner(fd)
                self._refuse(
                    fd,
                    f"{self.what}{self.file.parent} is being written by process {other.get('pid', '?')} on "
                    f"{other.get('host', 'this host')}; wait for it or stop it first",
                )
            try:  # a holder that released (unlinked) the file between our open and flock: retry on the new file
                same = os.fstat(fd).st_ino == os.stat(self.file).st_ino
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            other = self._owner(fd)
            pid = other.get("pid", -1)
            pid = pid if isinstance(pid, int) else -1
            if other.get("host") == me["host"] and pid != me["pid"] and _pid_alive(pid):
                self._refuse(
                    fd,
                    f"{self.what}{self.file.parent} is being written by process {pid} on this host; "
                    "wait for it or stop it first",
                )
            if other.get("host") not in (None, me["host"]):
                self._refuse(
                    fd,
                    f"{self.what}{self.file.parent} is locked by {other.get('host')}:{other.get('pid')}; if "
                    f"that run is gone, delete {self.file}",
                )
            if other:
                logger.info("taking over the lock %s of a run that is gone (%s)", self.file, other)
            os.ftruncate(fd, 0)
            os.lseek(fd, 0, os.SEEK_SET)
            os.write(fd, json.dumps(me).encode())
            os.fsync(fd)
            self._fd, self.held = fd, True
            return self
        raise DatasetError(f"could not take the lock {self.file}")

    def __exit__(self, *exc) -> None:
        if self.held:
            # Unlinked while still locked; a run that opened the old file meanwhile sees the
            # inode change after its flock and retries on a new file.
            self.file.unlink(missing_ok=True)
            os.close(self._fd)
            self._fd, self.held = None, False


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    # A zombie (killed, not yet reaped by its parent) still answers kill(0).
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return True


__all__ = ["DatasetLock"]
