"""One numba cache directory per version of the jitted source (see `ptw_rt/__init__.py` for why).

The base is `NUMBA_CACHE_DIR` if set (the systemd unit sets it under `CacheDirectory=`), else
`$XDG_CACHE_HOME/ptw-rt/numba` (`~/.cache/ptw-rt/numba`). Below it, `src-<hash>` holds the cache of one
version of `ptw_rt/core`, `edge`, `io` and `sim` (the packages with jitted code), marked as ours; marked
directories of other versions that nobody touched for an hour are removed, so upgrades do not accumulate caches
(nothing else is ever removed).
When the base cannot be written (a read-only home), the keyed directory goes below a private
`ptw-rt-numba-<uid>` in the temporary directory instead (never numba's own fallback, `__pycache__` beside the
source, which is not keyed), and the compile note says so.
Nothing here may raise: a cache problem costs one slow start, never a failed one.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import stat
import tempfile
import time
from pathlib import Path

JITTED_PACKAGES = ("core", "edge", "io", "sim")
_PREFIX = "src-"
_KEY = re.compile(r"src-[0-9a-f]{16}")
# written into each keyed directory: only directories that hold it are ever removed (a NUMBA_CACHE_DIR of /tmp, or
# one naming a directory of its own called src-something, had every src-* directory beside it removed)
_MARKER = ".ptw-rt-numba-cache"
_STALE_AFTER_S = 3600.0
_ENV = "NUMBA_CACHE_DIR"


def source_key() -> str:
    """Hash of every module of the jitted packages (names and contents)."""
    root = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for package in JITTED_PACKAGES:
        for path in sorted((root / package).glob("*.py")):
            digest.update(path.name.encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def _default_base() -> Path:
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "ptw-rt" / "numba"


# why the keyed directory is not below the configured base (it could not be written), for the compile note
_FALLBACK_REASON: str | None = None
_NOWHERE = False  # neither could be written: numba compiles on every start


def _owned_private_dir(path: Path) -> bool:
    """``path`` is a real directory of this user that nobody else may write: numba loads machine code from the
    cache, so a directory another user planted (in /tmp) would be code they run as us."""
    st = path.lstat()
    return stat.S_ISDIR(st.st_mode) and st.st_uid == os.geteuid() and not st.st_mode & 0o022


def _fallback_base() -> Path:
    return Path(tempfile.gettempdir()) / f"ptw-rt-numba-{os.geteuid()}"


def key_numba_cache_to_source() -> None:
    global _FALLBACK_REASON, _NOWHERE
    try:
        base = Path(os.environ.get(_ENV) or _default_base())
        if _KEY.fullmatch(base.name) and (base / _MARKER).is_file():  # keyed already (a child process)
            base = base.parent
        key = _PREFIX + source_key()
        try:
            (base / key).mkdir(parents=True, exist_ok=True)
            (base / key / _MARKER).touch()
        except OSError as exc:
            # a read-only home or cache directory: numba would fall back to __pycache__ beside the source, which is
            # not keyed (a changed callee's stale machine code would run) -- a private keyed directory in the
            # temporary directory instead (compiled again after a reboot when that is a tmpfs)
            fallback = _fallback_base()
            try:
                fallback.mkdir(mode=0o700, exist_ok=True)
                if not _owned_private_dir(fallback):
                    raise PermissionError(f"{fallback} is not a private directory of this user")
                (fallback / key).mkdir(exist_ok=True)
                (fallback / key / _MARKER).touch()
            except OSError as exc2:
                _FALLBACK_REASON = f"{base} cannot be written ({exc.strerror or exc}), nor {fallback} ({exc2})"
                _NOWHERE = True
                os.environ[_ENV] = str(base / key)  # numba finds its own place; nothing of ours to tidy
                return
            _FALLBACK_REASON = f"{base} cannot be written: {exc.strerror or exc}"
            base = fallback
        os.environ[_ENV] = str(base / key)
        _remove_other_versions(base, key)
    except Exception:  # noqa: BLE001 - never fail an import over a cache
        pass
    _tell_numba_if_imported()


def _tell_numba_if_imported() -> None:
    """numba reads NUMBA_CACHE_DIR when it is imported, and each `cache=True` function picks its cache directory
    when it is decorated. A program that imported numba before ptw_rt (a user's script, a notebook) would have
    every ptw_rt function cache in `__pycache__` beside the source, unkeyed: stale machine code of a changed callee
    ran (a profiling script died in `drive_block` with a division by zero, 2026-11-27). numba's own way to re-read its
    environment makes the keyed directory count before any ptw_rt function is decorated."""
    import sys

    config = sys.modules.get("numba.core.config")
    if config is not None:
        try:
            config.reload_config()
        except Exception:  # noqa: BLE001 - never fail an import over a cache
            pass


def _remove_other_versions(base: Path, keep: str) -> None:
    if not base.is_dir():
        return
    now = time.time()
    for entry in base.iterdir():
        if not _KEY.fullmatch(entry.name) or entry.name == keep or entry.is_symlink() or not entry.is_dir():
            continue
        try:
            if (entry / _MARKER).is_file() and now - entry.stat().st_mtime > _STALE_AFTER_S:
                shutil.rmtree(entry, ignore_errors=True)
        except OSError:
            pass


def is_cold(module: str = "estimator") -> bool:
    """True when the jitted functions of ``ptw_rt/core/<module>.py`` have no cached machine code for this version
    of the source (the first run after an install or an upgrade: compiling takes about 40 s). False when the
    cache cannot be known or numba's JIT is off (nothing to compile)."""
    try:
        if os.environ.get("NUMBA_DISABLE_JIT", "0") not in ("", "0"):
            return False
        base = os.environ.get(_ENV)
        if not base:
            return False
        return not any(Path(base).glob(f"*/{module}.*.nbi"))
    except Exception:  # noqa: BLE001 - never fail over a cache
        return False


COMPILING_NOTE = "compiling the estimator, about 40 s, once (numba cache: {cache})"


def announce_compile(stream=None) -> bool:
    """Print the one line a user waiting on a cold cache needs (stderr); True if printed."""
    import sys

    if not is_cold():
        return False
    stream = stream if stream is not None else sys.stderr
    try:
        note = COMPILING_NOTE.format(cache=os.environ.get(_ENV, "?"))
        if _NOWHERE:
            note = note.replace(", once (", ", on every start (")
        if _FALLBACK_REASON is not None:
            note = f"{note[:-1]}; {_FALLBACK_REASON})"
        stream.write(note + "\n")
        stream.flush()
    except (OSError, ValueError):
        return False
    return True
