"""Free flight of parcels in a triply periodic box and the granular temperature of the parcels.

- drift (ballistic, no force): ``x <- x + v dt`` (the move between collision resolutions of
  ``cases/homogeneous_cooling.py``; the swept surrogate adds its in-step position corrections after it);
- kick by a held acceleration: ``v <- v + a dt`` (the KTGF collision acceleration of ``kernels/ktgf.py``);
- wrap into the periodic box ``[0, L_a)`` per axis: ``x_a <- x_a - L_a floor(x_a / L_a)``;
- velocity moments of the real particles, parcel weight w (real particles per parcel):
  ``S0 = sum w``, ``S1 = sum w v``, ``S2 = sum w |v|^2`` (float64), from which the granular temperature
  ``Theta = <|v - <v>|^2> / 3 = (S2 - |S1|^2 / S0) / (3 S0)`` (m^2/s^2; Brilliantov & Poeschel,
  *Kinetic Theory of Granular Gases*, 2004, ch. 2). One row of ``moments`` per recorded step, so the
  whole history stays on the device until it is read once.

Removed parcels (``alive == 0``) neither move nor count. The moments are float64 atomic sums, compiled with Warp's
deterministic atomics (``DeterministicMode.RUN_TO_RUN``, Warp >= 1.19): on the CPU they are accumulated in index
order anyway; on CUDA the additions are ordered independently of the thread schedule, so that two runs of one seed
give the same Theta(t) to the last bit (on an H200 without it, the weight-8 cooling box of one seed gave Theta
series differing by ~1e-15 relative with every collision count equal).
"""

from __future__ import annotations

import warp as wp

if hasattr(wp.config, "DeterministicMode"):
    wp.set_module_options({"deterministic": wp.config.DeterministicMode.RUN_TO_RUN})


@wp.kernel
def add_rate_kernel(
    rate: wp.array(dtype=wp.vec3),
    particle_alive: wp.array(dtype=wp.int32),
    dt: float,
    # outputs
    value: wp.array(dtype=wp.vec3),
):
    """value += rate dt for live parcels (the drift x += v dt and the kick v += a dt)."""
    i = wp.tid()
    if particle_alive[i] == 0:
        return
    value[i] = value[i] + rate[i] * dt


@wp.func
def wrap_coordinate(x: float, length: float):
    """x - L floor(x / L), in [0, L) (a value rounding to L in float32 is set to 0)."""
    y = x - length * wp.floor(x / length)
    if y >= length:
        y = 0.0
    return y


@wp.kernel
def wrap_kernel(
    box_length: wp.vec3,
    particle_alive: wp.array(dtype=wp.int32),
    # outputs
    particle_x: wp.array(dtype=wp.vec3),
):
    i = wp.tid()
    if particle_alive[i] == 0:
        return
    x = particle_x[i]
    particle_x[i] = wp.vec3(wrap_coordinate(x[0], box_length[0]), wrap_coordinate(x[1], box_length[1]),
                            wrap_coordinate(x[2], box_length[2]))


@wp.kernel
def wrap_axes_kernel(
    origin: wp.vec3,
    box_length: wp.vec3,
    periodic: wp.vec3i,
    particle_alive: wp.array(dtype=wp.int32),
    # outputs
    particle_x: wp.array(dtype=wp.vec3),
):
    """Positions wrapped into [origin_a, origin_a + L_a) on the periodic axes only (a HEL grid periodic along
    some axes, walls or open boundaries on the others)."""
    i = wp.tid()
    if particle_alive[i] == 0:
        return
    x = particle_x[i]
    for a in range(3):
        if periodic[a] != 0:
            x[a] = origin[a] + wrap_coordinate(x[a] - origin[a], box_length[a])
    particle_x[i] = x


@wp.kernel
def velocity_moments_kernel(
    particle_v: wp.array(dtype=wp.vec3),
    particle_weight: wp.array(dtype=wp.float32),
    particle_alive: wp.array(dtype=wp.int32),
    row: int,
    # outputs
    moments: wp.array2d(dtype=wp.float64),
):
    """Row ``row`` of ``moments`` (rows, 5) += (w, w v_x, w v_y, w v_z, w |v|^2); zero the row first."""
    i = wp.tid()
    if particle_alive[i] == 0:
        return
    w = wp.float64(particle_weight[i])
    v = particle_v[i]
    vx = wp.float64(v[0])
    vy = wp.float64(v[1])
    vz = wp.float64(v[2])
    wp.atomic_add(moments, row, 0, w)
    wp.atomic_add(moments, row, 1, w * vx)
    wp.atomic_add(moments, row, 2, w * vy)
    wp.atomic_add(moments, row, 3, w * vz)
    wp.atomic_add(moments, row, 4, w * (vx * vx + vy * vy + vz * vz))


# ------------------------------------------------------------------------------------------ launch wrappers

def drift(particle_x, particle_v, particle_alive, dt: float) -> None:
    """x += v dt in place (live parcels)."""
    wp.launch(add_rate_kernel, dim=particle_x.shape[0], device=particle_x.device,
              inputs=[particle_v, particle_alive, float(dt)], outputs=[particle_x])


def kick(particle_v, particle_a, particle_alive, dt: float) -> None:
    """v += a dt in place (live parcels)."""
    wp.launch(add_rate_kernel, dim=particle_v.shape[0], device=particle_v.device,
              inputs=[particle_a, particle_alive, float(dt)], outputs=[particle_v])


def wrap_periodic(particle_x, particle_alive, box_length) -> None:
    """Positions wrapped into [0, L_a) per axis in place; ``box_length`` (3,) m."""
    wp.launch(wrap_kernel, dim=particle_x.shape[0], device=particle_x.device,
              inputs=[wp.vec3(*[float(b) for b in box_length]), particle_alive], outputs=[particle_x])


def wrap_axes(particle_x, particle_alive, origin, box_length, periodic) -> None:
    """Positions wrapped into the box per periodic axis in place (``periodic``: three flags)."""
    wp.launch(wrap_axes_kernel, dim=particle_x.shape[0], device=particle_x.device,
              inputs=[wp.vec3(*[float(o) for o in origin]), wp.vec3(*[float(b) for b in box_length]),
                      wp.vec3i(*[int(bool(p)) for p in periodic]), particle_alive], outputs=[particle_x])


def velocity_moments(particle_v, particle_weight, particle_alive, moments, row: int) -> None:
    """Row ``row`` of the float64 (rows, 5) array ``moments`` = (S0, S1x, S1y, S1z, S2) of the live parcels."""
    moments[row].zero_()
    wp.launch(velocity_moments_kernel, dim=particle_v.shape[0], device=particle_v.device,
              inputs=[particle_v, particle_weight, particle_alive, int(row)], outputs=[moments])
