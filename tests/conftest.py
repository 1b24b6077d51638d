"""Shared fixtures: every test runs on the device clflow selects ($CLFLOW_DEVICE or default,
PoCL's CPU device on CI)."""

import pytest


@pytest.fixture(scope="session")
def device():
    from clflow.runtime import get_device

    return get_device()
