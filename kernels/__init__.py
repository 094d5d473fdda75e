"""Warp kernels and ``@wp.func``s only, one file per physics concern (see docs/developer/architecture.md)."""
