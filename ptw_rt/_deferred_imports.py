"""Two imports no command needs at its start, deferred: python-can's MF4 support, and numba's probe for scipy.

``import can`` (and ``import cantools``, which imports ``can``) executes ``can.io.mf4``, which imports ``asammdf``
when it is installed, and asammdf imports pandas: 0.2 s and ~60 MB at every start of every command, the daemon
included, for a format most runs never touch. The finder below (installed by the command line, ``ptw_rt.cli.main``,
before anything imports python-can; a program importing ptw_rt as a library keeps python-can as it is) makes
the import of asammdf fail while, and only while, ``can.io.mf4`` is first executed: python-can then sets MF4 up
as absent. ``mf4()`` imports asammdf and executes ``can.io.mf4`` again: from then on it has MF4 support (its classes,
old and new, read the module's globals). Nothing else is affected: asammdf imported by anyone else, or before,
is imported as usual.

``import numba`` executes ``numba.np.arraymath``, whose ``_check_blas`` imports ``scipy.linalg`` to learn whether
BLAS is there for the jitted ``np.dot`` family: 0.2-0.3 s at every start where scipy is installed (the design,
test and evaluation environments), for a compiled path that never calls BLAS (the hot path's algebra is written
out). While ``numba.np.arraymath`` is first executed, scipy fails to import: numba sets up its pure fallback for
the one inner product that looks at the probe, and any jitted call of np.dot/np.linalg still imports scipy when
it is compiled (``numba.np.linalg.ensure_blas``). scipy imported by anyone else, or before, is imported as usual.
"""

from __future__ import annotations

import importlib
import importlib.abc
import sys
from types import ModuleType

_MF4 = "can.io.mf4"
_NUMBA_ARRAYMATH = "numba.np.arraymath"
# top-level package -> the module during whose first execution it is not imported
DEFERRED = {"asammdf": _MF4, "scipy": _NUMBA_ARRAYMATH}


def _executing(module: str) -> bool:
    spec = getattr(sys.modules.get(module), "__spec__", None)
    return spec is not None and bool(getattr(spec, "_initializing", False))


class _DeferImports(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):  # noqa: ANN001, ANN201 - importlib's protocol
        importer = DEFERRED.get(name.partition(".")[0])
        if importer is not None and _executing(importer):
            raise ModuleNotFoundError(f"{name} is imported when it is needed (ptw_rt._deferred_imports)")
        return None


FINDER = _DeferImports()


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
