"""Device-side NaN/inf detection: one reduction per array, one small int array read back per check.

Used at output intervals (not per step) to catch a blown-up field before it is written:
``count_nonfinite`` adds the number of non-finite entries of an array to ``bad[slot]``.
"""

import warp as wp


@wp.kernel
def nonfinite_float_kernel(values: wp.array(dtype=float), slot: int,
                           # outputs
                           bad: wp.array(dtype=wp.int32)):
    tid = wp.tid()
    if not wp.isfinite(values[tid]):
        wp.atomic_add(bad, slot, 1)


@wp.kernel
def nonfinite_vec3_kernel(values: wp.array(dtype=wp.vec3), slot: int,
                          # outputs
                          bad: wp.array(dtype=wp.int32)):
    tid = wp.tid()
    if not wp.isfinite(values[tid]):
        wp.atomic_add(bad, slot, 1)


@wp.kernel
def nonfinite_float64_kernel(values: wp.array(dtype=wp.float64), slot: int,
                             # outputs
                             bad: wp.array(dtype=wp.int32)):
    tid = wp.tid()
    if not wp.isfinite(values[tid]):
        wp.atomic_add(bad, slot, 1)


@wp.kernel
def nonfinite_vec3d_kernel(values: wp.array(dtype=wp.vec3d), slot: int,
                           # outputs
                           bad: wp.array(dtype=wp.int32)):
    tid = wp.tid()
    if not wp.isfinite(values[tid]):
        wp.atomic_add(bad, slot, 1)


_KERNELS = {wp.float32: nonfinite_float_kernel, wp.vec3: nonfinite_vec3_kernel,
            wp.float64: nonfinite_float64_kernel, wp.vec3d: nonfinite_vec3d_kernel}


def count_nonfinite(values, bad, slot: int = 0) -> None:
    """``bad[slot]`` += number of NaN/inf entries of ``values`` (any shape; float32/64, vec3, vec3d)."""
    kernel = _KERNELS.get(values.dtype)
    if kernel is None:
        raise TypeError(f"count_nonfinite: unsupported dtype {values.dtype}")
    flat = values.flatten() if values.ndim > 1 else values
    wp.launch(kernel, dim=flat.shape[0], device=values.device, inputs=[flat, int(slot)], outputs=[bad])
