"""One writer per run folder: ``RUN_DIR/.lock`` names the process that holds it.

Two ``slam run`` (or ``--resume``, ``--overwrite``) on one folder at once would each delete or
overwrite the other's files; the second is refused instead, with a message naming the holder.
The lock is a file created exclusively (``O_CREAT | O_EXCL``) holding the holder's pid, host
and start time. A lock whose process is gone (same host, no such pid) is stale: a killed run
leaves one behind, and the next run takes it over (and says so in the log).
"""

from __future__ import annotations

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


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process: alive
        return True
    return True


class RunLock:
    """The claim of this process on a run folder (a context manager; see the module
    docstring)."""

    def __init__(self, run_dir: str | Path) -> None:
        self.path = Path(run_dir) / LOCK_FILE
        self.held = False

    def _holder(self) -> dict:
        try:
            data = json.loads(self.path.read_text())
        except (OSError, ValueError):
            return {}
        return data if isinstance(data, dict) else {}

    def acquire(self) -> RunLock:
        me = {"pid": os.getpid(), "host": socket.gethostname(), "started": time.time()}
        for _ in range(3):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                holder = self._holder()
                pid, host = holder.get("pid"), holder.get("host")
                if host == me["host"] and isinstance(pid, int) and not _alive(pid):
                    log.warning(
                        "%s: taking over the lock of process %d, which is gone", self.path, pid
                    )
                    self.path.unlink(missing_ok=True)
                    continue
                if not holder:  # being written this instant, or unreadable: look once more
                    time.sleep(0.05)
                    holder = self._holder()
                    if not holder:
                        continue
                when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(holder.get("started", 0)))
                raise RunFolderError(
                    f"{self.path.parent} is in use by another run (pid {pid} on {host}, since "
                    f"{when}): wait for it to finish, or choose another --out; if that process "
                    f"is gone, delete {self.path}"
                ) from None
            with os.fdopen(fd, "w") as f:
                json.dump(me, f)
            self.held = True
            return self
        raise RunFolderError(f"{self.path}: cannot take the run folder's lock; delete it and retry")

    def release(self) -> None:
        if self.held:
            self.path.unlink(missing_ok=True)
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
