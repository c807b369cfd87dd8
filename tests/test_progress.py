"""Progress on stderr (issue #15, part 4): a bar on a terminal, plain periodic lines otherwise, and the one line
a user waiting on a cold numba cache gets."""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

from ptw_rt import _numba_cache
from ptw_rt.progress import Progress


class Tty(io.StringIO):
    def isatty(self):
        return True


def test_share_of_one_job_on_a_terminal():
    buf = Tty()
    p = Progress(1.0, label="replay ride.blf", stream=buf, interval=0.0)
    p.update(0.5)
    p.update(0.75)
    p.finish()
    out = buf.getvalue()
    assert out.count("\r") == 3 and " 50%" in out and " 75%" in out and "100%" in out and out.endswith("\n")


def test_a_short_job_shows_nothing():
    for stream in (Tty(), io.StringIO()):
        p = Progress(1.0, stream=stream, delay=60.0)
        p.update(0.5)
        p.finish()
        assert stream.getvalue() == ""


def test_plain_lines_when_not_a_terminal():
    buf = io.StringIO()
    p = Progress(1.0, label="replay x.log", stream=buf, every=0.0)
    p.update(0.25)
    p.update(0.5)
    p.finish()
    lines = buf.getvalue().splitlines()
    assert lines[0].startswith("replay x.log:  25% done") and lines[-1].startswith("replay x.log: done")
    assert "\r" not in buf.getvalue()


def test_cold_cache_is_announced_once(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("NUMBA_DISABLE_JIT", raising=False)
    buf = io.StringIO()
    assert _numba_cache.is_cold() and _numba_cache.announce_compile(buf)
    assert buf.getvalue() == f"compiling the estimator, about 40 s, once (numba cache: {tmp_path})\n"
    (tmp_path / "core_0123").mkdir()
    (tmp_path / "core_0123" / "estimator.estimator_step-242.py311.nbi").write_bytes(b"")
    assert not _numba_cache.is_cold() and not _numba_cache.announce_compile(io.StringIO())
    monkeypatch.setenv("NUMBA_DISABLE_JIT", "1")
    (tmp_path / "core_0123" / "estimator.estimator_step-242.py311.nbi").unlink()
    assert not _numba_cache.is_cold()


def test_the_running_cache_is_warm_after_a_step():
    """The test session has run the estimator: its cache directory (keyed to the source) has the index files."""
    from ptw_rt.edge.cycle import build_runner
    from ptw_rt.paths import DEFAULT_CONFIG

    build_runner(DEFAULT_CONFIG).cycle(0.0)
    if os.environ.get("NUMBA_DISABLE_JIT", "0") in ("", "0"):
        assert not _numba_cache.is_cold()


def test_only_our_own_cache_directories_are_ever_removed(tmp_path, monkeypatch):
    """A NUMBA_CACHE_DIR of /tmp (or one naming a directory called src-something) had every src-* directory beside
    it older than an hour removed at import. Only directories we keyed and marked are."""
    import os
    import time

    old = time.time() - 2 * 3600
    ours, theirs, named = tmp_path / "src-0123456789abcdef", tmp_path / "src-0123456789abcdee", tmp_path / "src-x"
    for d in (ours, theirs, named):
        d.mkdir()
    (ours / _numba_cache._MARKER).touch()
    for d in (ours, theirs, named):
        os.utime(d, (old, old))
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(named))  # a user's directory that happens to be called src-x
    _numba_cache.key_numba_cache_to_source()
    assert named.is_dir() and theirs.is_dir()  # not ours: kept
    assert os.environ["NUMBA_CACHE_DIR"].startswith(str(named))  # keyed below it, not beside it
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    _numba_cache.key_numba_cache_to_source()
    assert not ours.exists() and theirs.is_dir() and named.is_dir()  # ours, stale: removed; nothing else


def test_a_cache_directory_that_cannot_be_written_falls_back_to_a_private_keyed_one(tmp_path, monkeypatch):
    """A read-only home left NUMBA_CACHE_DIR naming a directory that could not be made: numba fell back to
    __pycache__ beside the source (not keyed to the source: a changed callee's stale code could run) while the note
    said "once" and named the unwritable path."""
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(blocker / "cache"))  # below a file: cannot be made
    monkeypatch.delenv("NUMBA_DISABLE_JIT", raising=False)
    monkeypatch.setattr(_numba_cache.tempfile, "gettempdir", lambda: str(tmp_path / "tmp"))
    monkeypatch.setattr(_numba_cache, "_FALLBACK_REASON", None)
    monkeypatch.setattr(_numba_cache, "_NOWHERE", False)
    (tmp_path / "tmp").mkdir()
    _numba_cache.key_numba_cache_to_source()
    private = tmp_path / "tmp" / f"ptw-rt-numba-{os.geteuid()}"
    keyed = os.environ["NUMBA_CACHE_DIR"]
    assert keyed == str(private / f"src-{_numba_cache.source_key()}") and os.path.isdir(keyed)
    assert private.stat().st_mode & 0o777 == 0o700
    buf = io.StringIO()
    assert _numba_cache.announce_compile(buf)
    assert f"once (numba cache: {keyed}; {blocker / 'cache'} cannot be written" in buf.getvalue()


def test_a_planted_shared_fallback_directory_is_never_used(tmp_path, monkeypatch):
    """Numba loads machine code from its cache: a fallback directory in /tmp that another user could write is code
    they would run as us. It is refused, and the note says the estimator compiles on every start."""
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(blocker / "cache"))
    monkeypatch.delenv("NUMBA_DISABLE_JIT", raising=False)
    monkeypatch.setattr(_numba_cache.tempfile, "gettempdir", lambda: str(tmp_path))
    monkeypatch.setattr(_numba_cache, "_FALLBACK_REASON", None)
    monkeypatch.setattr(_numba_cache, "_NOWHERE", False)
    planted = tmp_path / f"ptw-rt-numba-{os.geteuid()}"
    planted.mkdir()
    planted.chmod(0o777)
    _numba_cache.key_numba_cache_to_source()
    assert not os.environ["NUMBA_CACHE_DIR"].startswith(str(planted)) and not any(planted.iterdir())
    buf = io.StringIO()
    assert _numba_cache.announce_compile(buf)
    assert "on every start" in buf.getvalue() and "not a private directory" in buf.getvalue()


def test_a_program_that_imported_numba_first_still_caches_in_the_keyed_directory(tmp_path):
    """numba picks each function's cache directory when it is decorated, from the NUMBA_CACHE_DIR it read when it
    was imported: a script that imported numba before ptw_rt cached ptw_rt's code in `__pycache__` beside the
    source, unkeyed, and ran a changed callee's stale machine code (a division by zero in `drive_block`)."""
    code = (
        "import numba\nimport ptw_rt, os\nfrom ptw_rt.core import tyre_bank\n"
        "tyre_bank.state_size(4)\nprint(os.environ['NUMBA_CACHE_DIR'])\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["XDG_CACHE_HOME"] = str(tmp_path)
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    keyed = Path(done.stdout.strip())
    assert keyed.parent == tmp_path / "ptw-rt" / "numba"
    assert list(keyed.glob("*/tyre_bank.state_size-*.nbi")), sorted(str(p) for p in keyed.rglob("*"))
