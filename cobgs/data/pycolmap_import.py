"""pycolmap, imported without glog's failure-signal handler on SIGTERM.

COLMAP's glog installs a handler that prints a stack dump ("*** SIGTERM received by PID ...;
stack trace: ***") for SIGTERM, the signal a user, a scheduler or ``timeout`` sends to stop a
run cleanly. Right after pycolmap's first import in the main thread, SIGTERM gets back the
handler it had before (Python's default: end the process); the dumps of real crashes
(SIGSEGV, SIGABRT ...) are kept.
"""

from __future__ import annotations

import signal
import sys
import threading
from typing import Any


def import_pycolmap() -> Any:
    """``import pycolmap``, then SIGTERM's previous handler restored (module docstring)."""
    first = "pycolmap" not in sys.modules
    main = threading.current_thread() is threading.main_thread()
    before = signal.getsignal(signal.SIGTERM) if first and main else None
    import pycolmap

    if first and main:
        signal.signal(signal.SIGTERM, before if before is not None else signal.SIG_DFL)
    return pycolmap
