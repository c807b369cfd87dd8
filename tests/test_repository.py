"""The repository keeps its promises to a new user: README commands, CI script, layout."""

from __future__ import annotations

import re
import shutil
import subprocess

import pytest

from ptw_rt.paths import PROJECT_ROOT

README = (PROJECT_ROOT / "README.md").read_text()
CI = (PROJECT_ROOT / ".ci" / "run").read_text()


def readme_commands() -> list[str]:
    return [line.strip() for line in README.splitlines() if line.startswith("    python3 -m venv")]


def test_readme_has_exactly_two_setup_commands():
    commands = readme_commands()
    assert len(commands) == 2
    assert commands[0].split("&&")[-1].strip().startswith("ptw-rt ")
    assert commands[1].endswith("python -m pytest")


def test_ci_runs_the_readme_test_command():
    install = re.search(r'TEST_INSTALL="([^"]+)"', CI).group(1)
    test_command = readme_commands()[1]
    assert test_command == f"{install.replace(' -q -e', ' -q -e')} && python -m pytest"
    assert "python -m pytest" in CI and "set -euo pipefail" in CI
    assert "-eq 5" in CI  # pytest's "no tests collected" is a failure


def test_layout_named_by_the_product_owner():
    for name in ("pyproject.toml", "ptw_rt", "config", "dbc", "tests"):
        assert (PROJECT_ROOT / name).exists(), name


def test_the_repository_root_holds_only_the_named_layout():
    """A stray download (wheels, logs) in the root is not source: c1505c8 committed 13 wheels."""
    git = shutil.which("git")
    if git is None or not (PROJECT_ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    tracked = subprocess.run(
        [git, "ls-files"], cwd=PROJECT_ROOT, capture_output=True, text=True, check=True, timeout=30
    ).stdout.split()
    top_level = {path.split("/", 1)[0] for path in tracked}
    expected = {".ci", ".gitignore", "README.md", "config", "dbc", "docs", "ptw_rt", "pyproject.toml"}
    expected |= {"systemd", "tests"}
    assert top_level <= expected, sorted(top_level - expected)
