"""Shared fixtures: Warp quiet, on the device named by HEL_WARP_DEVICE (default ``cpu``); HEL_WARP_FULL=1 runs the
full-size physics checks.

HEL_WARP_DEVICE=cuda (or cuda:N) makes that device Warp's default for the whole test run, so every test that
allocates without naming a device, or takes the ``device`` fixture, runs there (``scripts/gpu_check.sh`` runs the
device-agnostic subset this way). Without such a device the run stops at once with a one-line reason.
"""

import os

import pytest

FULL = os.environ.get("HEL_WARP_FULL", "0") == "1"
DEVICE = os.environ.get("HEL_WARP_DEVICE", "cpu").strip() or "cpu"


def pytest_configure(config):
    import warp as wp

    from hel_warp._warp import start_warp

    start_warp(cuda=DEVICE != "cpu")  # quiet; Warp's missing-driver line only when a CUDA device is asked for
    if DEVICE != "cpu" and not wp.is_cuda_available():
        raise pytest.UsageError(f"HEL_WARP_DEVICE={DEVICE}: Warp finds no CUDA device here; unset it to test on the CPU")
    try:
        wp.set_device(DEVICE)
    except Exception as exc:  # an unknown name such as cuda:7 on a one-GPU machine
        raise pytest.UsageError(f"HEL_WARP_DEVICE={DEVICE} is not a Warp device here ({exc})") from None


def pytest_report_header(config):
    return f"hel_warp test device: {DEVICE} (HEL_WARP_DEVICE)"


@pytest.fixture(scope="session")
def device():
    """The Warp device name the device-agnostic tests run on (HEL_WARP_DEVICE, default ``cpu``)."""
    return DEVICE


@pytest.fixture(scope="session")
def full_size():
    """True when the slow physics checks should run at full size (not in CI)."""
    return FULL
