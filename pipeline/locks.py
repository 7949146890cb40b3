"""Per-entry file locks (POSIX ``fcntl.lockf``), so two runs never write the same entry.

POSIX record locks are what NFS (through lockd / NFSv4) honours, unlike BSD ``flock`` on
some servers; the kernel (or the lock server) drops them when the holder dies, SIGKILL
included, so a crashed run never leaves a lock behind. Lock files are removed only by
``cache gc``, and only under the lock; a holder re-checks that its open file is still the
one at the path (same inode) so it never holds a lock on an unlinked file.
"""

from __future__ import annotations

import errno
import fcntl
import os
import socket
import time
from pathlib import Path
from typing import Callable, Optional


class EntryLock:
    """An exclusive lock on ``path``; use as a context manager or acquire()/release()."""

    def __init__(self, path: Path):
        self.path = path
        self._fd: Optional[int] = None

    def acquire(self, blocking: bool = True,
                on_wait: Optional[Callable[[str], None]] = None) -> bool:
        """Take the lock. Returns False if ``blocking`` is False and another process holds it.

        ``on_wait(holder)`` is called once before blocking, with the holder's description.
        """
        self.path.parent.mkdir(parents=True, exist_ok=True)
        warned = False
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
            try:
                try:
                    fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except OSError as exc:
                    if exc.errno not in (errno.EACCES, errno.EAGAIN):
                        raise
                    if not blocking:
                        os.close(fd)
                        return False
                    if on_wait is not None and not warned:
                        on_wait(self.holder())
                        warned = True
                    fcntl.lockf(fd, fcntl.LOCK_EX)  # interruptible by Ctrl-C
                if os.path.exists(self.path) and os.fstat(fd).st_ino == os.stat(self.path).st_ino:
                    break
                os.close(fd)  # gc unlinked the file while we waited: lock the new one
            except BaseException:
                os.close(fd)
                raise
        os.ftruncate(fd, 0)
        os.write(fd, f"{socket.gethostname()} pid {os.getpid()} since "
                     f"{time.strftime('%H:%M:%S')}\n".encode())
        self._fd = fd
        return True

    def holder(self) -> str:
        try:
            return self.path.read_text().strip() or "another process"
        except OSError:
            return "another process"

    def release(self, unlink: bool = False) -> None:
        if self._fd is None:
            return
        try:
            if unlink:
                try:
                    os.unlink(self.path)
                except FileNotFoundError:
                    pass
            fcntl.lockf(self._fd, fcntl.LOCK_UN)
        finally:
            os.close(self._fd)
            self._fd = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def __enter__(self) -> "EntryLock":
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists (what a leftover named after its writer's pid needs:
    a dead writer's temporary files may go)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
