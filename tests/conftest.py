"""Shared fixtures: Warp on the CPU device, quiet; HEL_WARP_FULL=1 runs the full-size physics checks."""

import os

import pytest

FULL = os.environ.get("HEL_WARP_FULL", "0") == "1"


def pytest_configure(config):
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    wp.init()


@pytest.fixture(scope="session")
def device():
    return "cpu"


@pytest.fixture(scope="session")
def full_size():
    """True when the slow physics checks should run at full size (not in CI)."""
    return FULL
