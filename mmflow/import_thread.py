"""Import a heavy package in a short-lived thread, so that its import pins no caller's frame.

pyuvdata's first import keeps the frames on the importing stack alive (some object it creates
while importing holds its import frames, and each frame holds its caller through ``f_back``). A
function that imported pyuvdata lazily and then read a file kept its locals for the life of the
process: ``mmflow.io.readers.read_metadata``'s 1 GB ``UVData`` of a 256-integration, 32,896-baseline
UVH5 file stayed resident on the driver of the paper-scale run (1.63 GB before CLEAN, 3.26 GB in
it). Imported in a thread, only the thread's own frames are pinned.
"""
import importlib
import sys
import threading


def import_in_thread(name):
    """``importlib.import_module(name)``, the first import made from a fresh thread's stack.

    An error of the import is raised here, in the caller's thread (the module is imported again).
    """
    if name not in sys.modules:
        t = threading.Thread(target=_quiet_import, args=(name,), name=f"import-{name}", daemon=True)
        t.start()
        t.join()
    return importlib.import_module(name)


def _quiet_import(name):
    try:
        importlib.import_module(name)
    except Exception:  # noqa: BLE001 -- raised again by the caller's own import
        pass
