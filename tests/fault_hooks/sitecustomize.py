"""Test-only fault injection into DC's own processes (tests/test_e2e_never_silent.py).

Python imports ``sitecustomize`` at start when it is on the path: a test puts this folder on the
PYTHONPATH of `dc-bringup`, whose server processes inherit it. With ``DC_TEST_FAULT`` set to
``module:Class.method``, that method raises ``RuntimeError`` the first time it is called in any of
those processes, once: the marker file ``DC_TEST_FAULT_ONCE`` is created atomically by the one that
raises, so a restarted process runs normally. With ``DC_TEST_FAULT_HANG`` set to a number of
seconds, that first call blocks that long instead (then runs the method): a hang. With
``DC_TEST_FAULT_SKIP`` set to n, the first n calls in each process run normally (a fault at the
second activate, not at start-up). With ``DC_TEST_FAULT_IN`` set to a server's module
(``dc_measurements.server``), only that server's process faults: a method several servers run (a
worker's) would otherwise fault in whichever calls it first. Nothing here is imported without
``DC_TEST_FAULT``. With ``DC_TEST_FAULT_GATE`` naming a FIFO, the call that faults first waits
for a byte from it: the test decides when the fault happens (once every record is in the server).
"""

from __future__ import annotations

import os
import sys

_SPEC = os.environ.get("DC_TEST_FAULT")
if _SPEC:
    import importlib
    import time
    from typing import Any

    _module_name, _, _qualified = _SPEC.partition(":")
    _class_name, _, _method_name = _qualified.partition(".")
    _owner = getattr(importlib.import_module(_module_name), _class_name)
    _original = getattr(_owner, _method_name)
    _marker = os.environ["DC_TEST_FAULT_ONCE"]
    _hang_s = float(os.environ.get("DC_TEST_FAULT_HANG", "0"))
    _skip = [int(os.environ.get("DC_TEST_FAULT_SKIP", "0"))]
    # runpy has made sys.argv[0] the file of the module run with -m by the time a method is called.
    _only_in = os.environ.get("DC_TEST_FAULT_IN", "").replace(".", os.sep)
    _gate = os.environ.get("DC_TEST_FAULT_GATE", "")

    def _raise_once(self: Any, *args: Any, **kwargs: Any) -> Any:
        if _only_in and _only_in not in sys.argv[0]:
            return _original(self, *args, **kwargs)
        if _skip[0] > 0:
            _skip[0] -= 1
            return _original(self, *args, **kwargs)
        try:
            os.close(os.open(_marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
        except FileExistsError:
            return _original(self, *args, **kwargs)
        if _gate:
            with open(_gate, "rb") as gate:
                gate.read(1)  # blocks until the test writes
        if _hang_s:
            time.sleep(_hang_s)  # the hang itself: nothing to wait for
            return _original(self, *args, **kwargs)
        raise RuntimeError(f"injected by the test into {_SPEC}")

    setattr(_owner, _method_name, _raise_once)
