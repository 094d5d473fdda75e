"""Recorded kernel launches, replayed (the parcel phase's per-call cost: many small launches per step).

``wp.launch`` packs every argument on every call: ~20-30 us per launch with the parcel kernels' structs on the
CPU, and the parcel phase makes ~20 launches per HEL step, ~50 ns per parcel at 1e4 parcels. A launch recorded
once (``wp.launch(..., record_cmd=True)``, a ``wp.Launch``) and replayed costs ~7 us. ``LaunchCache`` keeps one
recorded launch per kernel, launch size, device and argument set:

- an array is the same argument while it is the same object (the recorded launch holds it, so its id is not
  reused; an array's memory does not move);
- a struct is the same argument while its packed value is (``bytes`` of its ctype: a struct changed in place, or
  rebuilt with other values, is recorded again; rebuilt with the same values it hits);
- a scalar is the same argument while its value is.

A replayed launch passes the kernel exactly the values a fresh ``wp.launch`` would, so results do not change.
The cache holds its arguments alive: keep one per owner of the arrays (``CouplingFields.launches``); it is cleared
when it holds ``max_entries`` launches. CPU only: on a CUDA device, or during a graph capture, it calls
``wp.launch`` as before (a GPU queues launches asynchronously and captured graphs replay them anyway; the GPU path
stays the one that was tested there).
"""

from __future__ import annotations

import warp as wp


def _arg_key(arg):
    """What makes ``arg`` the same argument of a recorded launch (module docstring)."""
    if isinstance(arg, wp.array):
        return ("array", id(arg))
    ctype = getattr(arg, "_ctype", None)
    if ctype is not None:  # a Warp struct instance
        return ("struct", type(arg).__qualname__, bytes(ctype))
    if isinstance(arg, (bool, int, float)):
        return ("value", type(arg), arg)
    value = getattr(arg, "value", None)  # Warp scalar (wp.float64(...))
    if value is not None:
        return ("value", type(arg), value)
    return ("object", id(arg))


class LaunchCache:
    """Recorded launches by kernel, size, device and arguments (module docstring); :meth:`launch` replays one, or
    records it first."""

    def __init__(self, max_entries: int = 128):
        self.max_entries = int(max_entries)
        self._launches = {}

    def launch(self, kernel, *, dim, inputs, outputs, device) -> None:
        device = wp.get_device(device)
        if device.is_cuda or device.is_capturing:
            wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device)
            return
        args = (*inputs, *outputs)
        key = (kernel, tuple(dim) if isinstance(dim, (tuple, list)) else int(dim), device.alias,
               tuple(_arg_key(a) for a in args))
        entry = self._launches.get(key)
        if entry is None:
            if len(self._launches) >= self.max_entries:
                self._launches.clear()
            recorded = wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device, record_cmd=True)
            entry = self._launches[key] = (recorded, args)  # the arguments held: their ids are not reused
        entry[0].launch()

    def __len__(self) -> int:
        return len(self._launches)


def launch(kernel, *, dim, inputs, outputs, device, cache: LaunchCache | None = None) -> None:
    """``wp.launch`` (``cache`` None), or the cache's recorded launch of it."""
    if cache is None:
        wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device)
    else:
        cache.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device)
