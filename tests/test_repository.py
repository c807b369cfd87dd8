"""The repository keeps its promises to a new user: README commands, CI script, layout."""

from __future__ import annotations

import re

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
