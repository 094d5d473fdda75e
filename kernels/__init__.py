"""Warp kernels and ``@wp.func``s only, one file per physics concern (see ARCHITECTURE.md)."""
