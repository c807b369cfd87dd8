"""python-can without its MF4 support until a log needs it.

``import can`` (and ``import cantools``, which imports ``can``) executes ``can.io.mf4``, which imports ``asammdf``
when it is installed, and asammdf imports pandas: 0.2 s and ~60 MB at every start of every command, the daemon
included, for a format most runs never touch. The finder below (installed by the command line, ``ptw_rt.cli.main``,
before anything imports python-can; a program importing ptw_rt as a library keeps python-can as it is) makes
the import of asammdf fail while, and only while, ``can.io.mf4`` is first executed: python-can then sets MF4 up
as absent. ``mf4()`` imports asammdf and executes ``can.io.mf4`` again: from then on it has MF4 support (its classes,
old and new, read the module's globals). Nothing else is affected: asammdf imported by anyone else, or before,
is imported as usual.
"""

from __future__ import annotations

import importlib
import importlib.abc
import sys
from types import ModuleType

_MF4 = "can.io.mf4"


class _DeferAsammdf(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):  # noqa: ANN001, ANN201 - importlib's protocol
        if name == "asammdf":
            spec = getattr(sys.modules.get(_MF4), "__spec__", None)
            if spec is not None and getattr(spec, "_initializing", False):  # can.io.mf4 is executing
                raise ModuleNotFoundError("asammdf is imported when a log needs it (ptw_rt._deferred_imports)")
        return None


FINDER = _DeferAsammdf()


def install() -> None:
    if FINDER not in sys.meta_path:
        sys.meta_path.insert(0, FINDER)


def mf4() -> ModuleType:
    """``can.io.mf4`` with MF4 support if asammdf is installed (its ``asammdf`` is None when it is not)."""
    import can.io.mf4 as module

    if module.asammdf is None:
        try:
            importlib.import_module("asammdf")
        except ImportError:
            return module
        importlib.reload(module)
    return module
