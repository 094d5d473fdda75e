"""Errors that reach the user as one line (the CLI prints them and exits with code 2)."""


class HelWarpError(Exception):
    """Base class of every error hel_warp raises on purpose."""


class ConfigError(HelWarpError, ValueError):
    """Invalid input: the message says which value is wrong and what to change."""


def require_finite(name: str, value) -> None:
    """Raise ConfigError when ``value`` (scalar or array) holds NaN or infinity."""
    import numpy as np

    arr = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise ConfigError(f"{name} must be finite (got {value!r}); give a real number")


def require_positive(name: str, value: float, unit: str = "") -> None:
    """Raise ConfigError unless ``value`` is finite and > 0."""
    require_finite(name, value)
    if not value > 0:
        raise ConfigError(f"{name} must be > 0 (got {value!r}{' ' + unit if unit else ''}); give a positive value")


def finite_float(text: str) -> float:
    """argparse type: a finite float (NaN and infinity are refused with a one-line error)."""
    import argparse
    import math

    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be finite, got {text!r}")
    return value
