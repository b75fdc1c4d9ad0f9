"""One run per row at a time: an exclusive `fcntl.flock` on data/interim/<SEQ>/_manifest/lock.

The kernel drops a flock when the process holding it ends, however it ends (SIGKILL, out-of-memory
kill, power cut), so a killed run never leaves the row locked. The file's content (pid, start time,
command) is only there to name the holder in the error a second run gets; a stale content is
harmless because the lock itself is the flock, not the file.
"""
from __future__ import annotations

import datetime
import fcntl
import json
import os
import sys
from pathlib import Path

from pipeline import io


class RowLocked(RuntimeError):
    """Another process is running stages of the same row."""


def lock_path(data_root: Path, seq: str) -> Path:
    return Path(data_root) / "interim" / seq / "_manifest" / "lock"


class RowLock:
    """Context manager: holds the row's lock or raises RowLocked naming the holder."""

    def __init__(self, data_root: Path, seq: str):
        self.seq = seq
        self.path = lock_path(data_root, seq)
        self.fd: int | None = None
        self.depth = 0

    def acquire(self) -> "RowLock":
        if self.fd is not None:  # re-entrant within one process (Runner.run called again)
            self.depth += 1
            return self
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as err:  # read-only data/, a file where a folder should be, a full disk
            raise io.write_error(self.path, err) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _describe(fd)
            os.close(fd)
            raise RowLocked(f"row {self.seq} is being processed by {holder}; wait for it to finish or stop it "
                            f"(the lock is {self.path}; it is released when that process ends)") from None
        except OSError as err:  # a file system without flock: run unguarded rather than not at all
            os.close(fd)
            print(f"[pag] warning: cannot lock {self.path} ({err}); two runs of row {self.seq} would not be "
                  f"kept apart", file=sys.stderr)
            return self
        started = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
        info = json.dumps({"pid": os.getpid(), "started": started, "command": " ".join(sys.argv)[:500]})
        os.ftruncate(fd, 0)
        os.pwrite(fd, info.encode(), 0)
        self.fd, self.depth = fd, 1
        return self

    def release(self) -> None:
        if self.fd is None:
            return
        self.depth -= 1
        if self.depth > 0:
            return
        fcntl.flock(self.fd, fcntl.LOCK_UN)
        os.close(self.fd)
        self.fd = None

    def __enter__(self) -> "RowLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def _describe(fd: int) -> str:
    try:
        info = json.loads(os.pread(fd, 4096, 0).decode() or "{}")
    except (OSError, ValueError):
        info = {}
    if "pid" not in info:
        return "another process"
    return f"pid {info['pid']} (started {info.get('started', '?')})"
