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
