"""Device-side NaN/inf detection: one reduction per array, one small int array read back per check.

Used at output intervals (not per step) to catch a blown-up field before it is written:
``count_nonfinite`` adds the number of non-finite entries of an array to ``bad[slot]``.
"""

from typing import Any

import warp as wp


@wp.kernel
def nonfinite_kernel(values: wp.array(dtype=Any), slot: int,
                     # outputs
                     bad: wp.array(dtype=wp.int32)):
    tid = wp.tid()
    if not wp.isfinite(values[tid]):
        wp.atomic_add(bad, slot, 1)


_KERNELS = {dtype: wp.overload(nonfinite_kernel, [wp.array(dtype=dtype), int, wp.array(dtype=wp.int32)])
            for dtype in (wp.float32, wp.vec3, wp.float64, wp.vec3d)}


def count_nonfinite(values, bad, slot: int = 0) -> None:
    """``bad[slot]`` += number of NaN/inf entries of ``values`` (any shape; float32/64, vec3, vec3d)."""
    kernel = _KERNELS.get(values.dtype)
    if kernel is None:
        raise TypeError(f"count_nonfinite: unsupported dtype {values.dtype}")
    flat = values.flatten() if values.ndim > 1 else values
    wp.launch(kernel, dim=flat.shape[0], device=values.device, inputs=[flat, int(slot)], outputs=[bad])
