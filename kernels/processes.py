"""Child processes that die with their parent: `die_with_parent`.

A worker process (``tt generate --workers``' process pool, its queue's manager) must not
outlive the command that started it: killed with SIGKILL, the command gets no chance to
stop them, and an orphaned worker would go on writing shards for minutes. On Linux the
kernel's parent-death signal (``prctl(PR_SET_PDEATHSIG, SIGKILL)``) kills the child when
the thread that forked it ends; the pool's workers are forked by the command's main thread
(`concurrent.futures.ProcessPoolExecutor.submit` with the spawn context), which lives as
long as the process. A watcher thread that polls the parent's pid backs it up (other
systems, or a child forked by a thread that ends early).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import sys
import threading
import time

#: linux/prctl.h
PR_SET_PDEATHSIG = 1
#: Seconds between the watcher thread's checks of the parent.
PARENT_POLL_S = 0.5


def _set_pdeathsig(sig: int) -> bool:
    """Ask the kernel to send `sig` to this process when its parent (thread) dies; whether it took."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _die() -> None:
    os.kill(os.getpid(), signal.SIGKILL)  # at once, whatever the process is doing (no cleanup to wait for)


def die_with_parent(parent: int) -> None:
    """Make this (child) process die by SIGKILL as soon as `parent` stops being its parent:
    the parent-death signal, and a daemon thread polling ``os.getppid()``. A parent already
    gone (the child was re-parented before this call) kills it now."""
    _set_pdeathsig(signal.SIGKILL)
    if os.getppid() != parent:
        _die()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_POLL_S)
        _die()

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


__all__ = ["die_with_parent"]
