"""One writer per dataset folder: `DatasetLock`, the ``DATASET/.lock`` file `tt generate` holds.

The lock file holds the host name and pid of the writer. A lock whose process no longer
runs on this host (killed, or a zombie) is stale and taken over; a lock of another host is
never taken over (its run may still be going), and the error says which file to delete.
"""

from __future__ import annotations

import json
import os
import socket
from pathlib import Path

from tt.tokens.store import DatasetError


class DatasetLock:
    """One writer per dataset: ``DATASET/.lock`` holds host and pid of the running `tt generate`.

    A lock left by a process that no longer runs on this host (killed) is taken over.
    """

    def __init__(self, path: str | Path):
        self.file = Path(path) / ".lock"
        self.held = False

    def __enter__(self) -> "DatasetLock":
        me = {"host": socket.gethostname(), "pid": os.getpid()}
        for _ in range(2):
            try:
                fd = os.open(self.file, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            except FileExistsError:
                try:
                    other = json.loads(self.file.read_text())
                except (OSError, json.JSONDecodeError):
                    other = {}
                if other.get("host") == me["host"] and _pid_alive(int(other.get("pid", -1))):
                    raise DatasetError(f"{self.file.parent} is being written by process {other['pid']} on this host; "
                                       "wait for it or stop it first") from None
                if other.get("host") not in (None, me["host"]):
                    raise DatasetError(f"{self.file.parent} is locked by {other.get('host')}:{other.get('pid')}; if that "
                                       f"run is gone, delete {self.file}") from None
                self.file.unlink(missing_ok=True)  # stale: its process is gone
                continue
            with os.fdopen(fd, "w") as f:
                json.dump(me, f)
            self.held = True
            return self
        raise DatasetError(f"could not take the lock {self.file}")

    def __exit__(self, *exc) -> None:
        if self.held:
            self.file.unlink(missing_ok=True)
            self.held = False


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
