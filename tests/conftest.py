"""Shared fixtures: the default configuration and one fresh design per test session."""

from __future__ import annotations

import pytest

from ptw_rt.paths import DEFAULT_CONFIG
from ptw_rt.settings import load_settings


@pytest.fixture(scope="session")
def settings():
    return load_settings(DEFAULT_CONFIG)


@pytest.fixture(scope="session")
def vehicle(settings):
    return settings.vehicle


@pytest.fixture(scope="session")
def fresh_design(settings):
    from ptw_rt.design.build import make_design

    return make_design(settings)


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """One loud line when the SocketCAN integration tests did not run: why, and how to get them."""
    skipped = [r for r in terminalreporter.stats.get("skipped", []) if "vcan" in getattr(r, "keywords", {})]
    if not skipped:
        return
    reason = str(skipped[0].longrepr[2]) if isinstance(skipped[0].longrepr, tuple) else str(skipped[0].longrepr)
    reason = reason.removeprefix("Skipped: ")
    terminalreporter.write_line(
        f"SOCKETCAN INTEGRATION TESTS SKIPPED ({len(skipped)} tests, tests/test_vcan_integration.py): {reason}. "
        "To run them: sudo apt-get install user-mode-linux can-utils kmod iproute2 (User-Mode Linux boots a kernel "
        "with vcan when this one has none; .ci/run does this), or a kernel with the vcan module.",
        red=True,
        bold=True,
    )


@pytest.fixture(scope="session")
def design(settings):
    """The committed design file (what the daemon loads)."""
    from ptw_rt.design.file import load_design
    from ptw_rt.paths import DEFAULT_DESIGN

    return load_design(DEFAULT_DESIGN, settings.config_hash)
