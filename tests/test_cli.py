"""The command line's own promises: --version, help on every option, one line for a missing extra."""

from __future__ import annotations

import argparse
import subprocess
import sys

import pytest

from ptw_rt.cli import build_parser, main


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.startswith("ptw-rt ")


def test_every_option_has_help():
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    missing = [
        f"{name} {action.option_strings or action.dest}"
        for name, p in sub.choices.items()
        for action in p._actions
        if action.help is None
    ]
    assert not missing


@pytest.mark.parametrize("command", ["analyze", "design"])
def test_missing_design_extra_is_one_line(command):
    code = (
        "import sys; sys.modules['scipy'] = None; sys.modules['cvxpy'] = None\n"
        f"from ptw_rt.cli import main; sys.exit(main([{command!r}]))"
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in p.stderr, p.stderr
    assert f"ptw-rt {command}: needs the 'design' extra" in lines[0] and "pip install 'ptw-rt[design]'" in lines[0]


def test_a_command_starts_without_scipy_linalg_and_jitted_linear_algebra_still_compiles(tmp_path):
    """numba probes for BLAS by importing scipy.linalg when it is imported (0.2-0.4 s at every start where scipy
    is installed); the command line defers that probe (``ptw_rt._deferred_imports``). A replay then never loads
    scipy.linalg, and a jitted np.dot, which does need BLAS, still compiles and runs in the same process."""
    pytest.importorskip("scipy.linalg")  # nothing to defer where scipy is not installed
    log = tmp_path / "one.log"
    log.write_text("(0.000000) can0 100#0000000000000000\n")
    probe = (
        "import sys; from ptw_rt.cli import main\n"
        f"code = main(['replay', {str(log)!r}, '--out', {str(tmp_path / 'o.log')!r}, '--no-progress'])\n"
        "print('LINALG', 'scipy.linalg' in sys.modules, 'NUMBA', 'numba.np.arraymath' in sys.modules)\n"
        "import numpy as np; from numba import njit\n"
        "print('DOT', njit(lambda a, b: np.dot(a, b))(np.ones(3), np.arange(3.0)))\n"
    )
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300)
    assert "LINALG False NUMBA True" in done.stdout, done.stdout + done.stderr
    assert "DOT 3.0" in done.stdout, done.stdout + done.stderr
