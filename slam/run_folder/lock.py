"""One writer per run folder: ``RUN_DIR/.lock`` names the process that holds it.

Two ``slam run`` (or ``--resume``, ``--overwrite``) on one folder at once would each delete or
overwrite the other's files; the second is refused instead, with a message naming the holder.
The claim is the operating system's exclusive lock (``flock``) on that file, which the kernel
drops when its process ends, however it ends: a killed run's lock is free for the next run,
and of several processes taking over a free one at the same instant exactly one gets it (a
file created exclusively and unlinked when stale let two hold it). The file holds the
holder's pid, host and start time, for the message; a lock file naming a live process of this
host that does not hold the OS lock (written by an older version) is respected too.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import socket
import time
from pathlib import Path
from types import TracebackType

from slam.errors import RunFolderError
from slam.run_folder.layout import LOCK_FILE

log = logging.getLogger(__name__)


def _alive(pid: object) -> bool:
    """Whether ``pid`` names a live process (a pid that cannot be one is no process)."""
    if not isinstance(pid, int) or isinstance(pid, bool) or not 0 < pid < 2**31:
        return False
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):
        return False
    except PermissionError:  # another user's process: alive
        return True
    return True


def _when(started: object) -> str:
    """A holder's start time for the message (``started``: seconds since the epoch)."""
    if isinstance(started, (int, float)) and not isinstance(started, bool):
        try:
            return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(started))
        except (OverflowError, OSError, ValueError):
            pass
    return "an unknown time"


class RunLock:
    """The claim of this process on a run folder (a context manager; see the module
    docstring)."""

    def __init__(self, run_dir: str | Path) -> None:
        self.path = Path(run_dir) / LOCK_FILE
        self.held = False
        self._fd: int | None = None

    def _holder(self) -> dict:
        try:
            data = json.loads(self.path.read_text())
        except (OSError, ValueError, RecursionError):
            return {}
        return data if isinstance(data, dict) else {}

    def _in_use(self, holder: dict) -> RunFolderError:
        pid, host = holder.get("pid", "unknown"), holder.get("host", "unknown host")
        return RunFolderError(
            f"{self.path.parent} is in use by another run (pid {pid} on {host}, since "
            f"{_when(holder.get('started'))}): wait for it to finish, or choose another "
            f"--out; if that process is gone, delete {self.path}"
        )

    def acquire(self) -> RunLock:
        me = {"pid": os.getpid(), "host": socket.gethostname(), "started": time.time()}
        for _ in range(5):
            fd = os.open(self.path, os.O_CREAT | os.O_RDWR | os.O_CLOEXEC, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                holder = self._holder()
                if not holder:  # its holder is writing it this instant: look once more
                    time.sleep(0.05)
                    holder = self._holder()
                raise self._in_use(holder) from None
            try:  # the lock is on the file this descriptor opened: is it still the lock file?
                current = os.stat(self.path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:  # released (unlinked) between our open and our lock
                current = False
            if not current:
                os.close(fd)
                continue
            holder = self._holder()
            pid, host = holder.get("pid"), holder.get("host")
            if host == me["host"] and pid != me["pid"] and _alive(pid):
                os.close(fd)  # a live holder that does not use the OS lock
                raise self._in_use(holder)
            if holder:
                log.warning("%s: taking over the lock of process %s, which is gone", self.path, pid)
            os.ftruncate(fd, 0)
            os.write(fd, json.dumps(me).encode())
            self._fd = fd
            self.held = True
            return self
        raise RunFolderError(f"{self.path}: cannot take the run folder's lock; delete it and retry")

    def release(self) -> None:
        if self.held and self._fd is not None:
            self.path.unlink(missing_ok=True)  # before the OS lock goes: no one holds a lock
            os.close(self._fd)  # on a file about to vanish
            self._fd = None
            self.held = False

    def __enter__(self) -> RunLock:
        return self.acquire()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.release()
