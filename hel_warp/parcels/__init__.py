"""The parcels and their coupling to the gas.

- ``particles``: ``Particles``, the state of the spheres or parcels (Warp arrays on one device).
- ``pool``: ``ParcelPool``, a fixed-capacity pool with volume injection and outlet removal, parcel weights.
- ``coupling``: the two-way coupling of a HEL step: deposit to the cells, interpolation of the gas to the parcels,
  drag and the push.
"""

from hel_warp._lazy import exports

__getattr__, __dir__ = exports(__name__, {
    "Particles": "particles", "ParcelPool": "pool", "VolumeInjection": "pool", "GridSpec": "coupling",
    "PushConfig": "coupling", "CouplingFields": "coupling",
})
