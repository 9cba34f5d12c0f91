"""pycolmap, imported without the SIGTERM handler its logging library installs.

Importing pycolmap installs glog's failure signal handler, which answers SIGTERM (a batch
scheduler's time limit, ``timeout``, ``docker stop``) with a stack dump that reads as a crash and
ends the process before Python can remove its temporary files or say what happened. The
handler Python had for SIGTERM before the import is put back; glog keeps the crash signals
(SIGSEGV, SIGABRT, ...) where its dump helps. Standard library only until called.
"""
from __future__ import annotations

import signal
import threading
from types import ModuleType

_restored = False


def import_pycolmap() -> ModuleType:
    """The ``pycolmap`` module, SIGTERM left as Python had it (see the module's docstring)."""
    global _restored
    import pycolmap as module

    if not _restored and threading.current_thread() is threading.main_thread():
        # Python still reports its own handler (it does not see glog's); installing that one
        # again replaces glog's at the C level.
        handler = signal.getsignal(signal.SIGTERM)
        signal.signal(signal.SIGTERM, handler if handler is not None else signal.SIG_DFL)
        _restored = True
    return module
