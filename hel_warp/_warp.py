"""Warp start-up shared by the commands, cases and scripts: quiet logging, ``wp.init()``, a checked device."""

from __future__ import annotations

import contextlib

from hel_warp.errors import ConfigError

DRIVER_WARNING = "Could not find or load the NVIDIA CUDA driver"
"""The line Warp's native library prints on a machine without a CUDA driver (``init_cuda_driver`` in
``warp/native/cuda_util.cpp``, a C ``fprintf(stderr, ...)``: neither ``wp.config.quiet`` nor ``log_level`` reach it)."""


@contextlib.contextmanager
def _without_driver_warning():
    """File descriptor 2 into a temporary file while the block runs, then every line of it but Warp's
    missing-driver warning back onto stderr (the native library writes to the C stderr, not ``sys.stderr``)."""
    import os
    import sys
    import tempfile

    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        try:
            yield
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            held.seek(0)
            kept = [line for line in held.read().splitlines(keepends=True) if DRIVER_WARNING.encode() not in line]
            if kept:
                os.write(2, b"".join(kept))


def start_warp(*, cuda: bool = False) -> None:
    """``wp.init()`` once, without Warp's greeting or module-load lines.

    Unless ``cuda`` (the caller asks for a CUDA device), Warp's "Could not find or load the NVIDIA CUDA driver"
    warning is dropped: on a machine without a GPU every CPU run would print it, and a run that asks for CUDA there
    fails with its own one-line reason (``init_warp``, ``hel_warp.runs.run.check_device``).
    """
    import warp as wp

    if hasattr(wp, "LOG_WARNING"):  # Warp >= 1.19; wp.config.quiet is a no-op there
        wp.config.log_level = wp.LOG_WARNING
    else:
        wp.config.quiet = True
    if cuda:
        wp.init()
        return
    with _without_driver_warning():
        wp.init()


def init_warp(device=None):
    """Silence Warp's greeting and module-load lines, initialise Warp and return the device.

    ``device`` is a Warp device name (``"cpu"``, ``"cuda:0"``) or None for Warp's default device. Warp's
    missing-driver warning shows only when ``device`` names a CUDA device (``start_warp``).
    Raises ``ConfigError`` naming ``--device cpu`` when the device is not available here.
    """
    import warp as wp

    start_warp(cuda=device is not None and str(device).startswith("cuda"))
    try:
        return wp.get_device(device)
    except Exception:
        reason = "" if wp.is_cuda_available() else " (Warp finds no CUDA device: no GPU or no driver)"
        raise ConfigError(f"Warp device {device!r} is not available here{reason}; use --device cpu") from None
