"""Warp start-up shared by the commands, cases and scripts: quiet logging, ``wp.init()``, a checked device."""

from __future__ import annotations

from hel_warp.errors import ConfigError


def init_warp(device=None):
    """Silence Warp's greeting and module-load lines, initialise Warp and return the device.

    ``device`` is a Warp device name (``"cpu"``, ``"cuda:0"``) or None for Warp's default device.
    Raises ``ConfigError`` naming ``--device cpu`` when the device is not available here.
    """
    import warp as wp

    if hasattr(wp, "LOG_WARNING"):  # Warp >= 1.19; wp.config.quiet is a no-op there
        wp.config.log_level = wp.LOG_WARNING
    else:
        wp.config.quiet = True
    wp.init()
    try:
        return wp.get_device(device)
    except Exception:
        raise ConfigError(f"Warp device {device!r} is not available here; use --device cpu") from None
