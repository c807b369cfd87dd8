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
