"""Velocity Verlet for spheres: translation with gravity and rotation (Swope et al. 1982, J. Chem. Phys. 76: 637).

One step of size dt, with a(x, v) = F/m + g and alpha = T/I, I = 2/5 m r^2 (solid sphere):

    v <- v + a dt/2 ;  w <- w + alpha dt/2         (kick_drift: half kick ...)
    x <- x + v dt                                  (... and drift)
    F, T <- contact forces at the new x            (kernels/contacts.py, kernels/walls.py)
    v <- v + a dt/2 ;  w <- w + alpha dt/2         (kick)

Second order and symplectic for conservative forces; velocity-dependent (damping) forces are
evaluated with the half-step velocity. Removed particles (alive == 0) do not move.
"""

from __future__ import annotations

import warp as wp


@wp.struct
class SphereArrays:
    """The per-particle arrays DEM kernels read and update (views of ``hel_warp.parcels.particles.Particles``)."""

    x: wp.array(dtype=wp.vec3)
    """Centre positions, m."""
    v: wp.array(dtype=wp.vec3)
    """Velocities, m/s."""
    omega: wp.array(dtype=wp.vec3)
    """Angular velocities, rad/s."""
    radius: wp.array(dtype=wp.float32)
    """Radii, m."""
    density: wp.array(dtype=wp.float32)
    """Material densities, kg/m^3."""
    alive: wp.array(dtype=wp.int32)
    """1 while the particle takes part in the run."""


@wp.func
def sphere_mass(radius: float, density: float):
    """m = rho 4/3 pi r^3, kg."""
    return density * (4.0 / 3.0 * wp.pi) * radius * radius * radius


@wp.func
def half_kick(spheres: SphereArrays, i: int, force: wp.vec3, torque: wp.vec3, gravity: wp.vec3, dt: float):
    """v += (F/m + g) dt/2, omega += T dt / (2 I) with I = 2/5 m r^2 (solid sphere); returns the new v."""
    r = spheres.radius[i]
    m = sphere_mass(r, spheres.density[i])
    half_dt = 0.5 * dt
    v = spheres.v[i] + (force / m + gravity) * half_dt
    spheres.v[i] = v
    spheres.omega[i] = spheres.omega[i] + torque * (half_dt / (0.4 * m * r * r))
    return v


@wp.kernel
def kick_drift(
    particle_f: wp.array[wp.vec3],
    particle_torque: wp.array[wp.vec3],
    gravity: wp.vec3,
    dt: float,
    # outputs (x, v, omega updated in place)
    spheres: SphereArrays,
):
    """Half kick with the forces of the current positions, then a full drift."""
    i = wp.tid()
    if spheres.alive[i] == 0:
        return
    v = half_kick(spheres, i, particle_f[i], particle_torque[i], gravity, dt)
    spheres.x[i] = spheres.x[i] + v * dt


@wp.kernel
def kick(
    particle_f: wp.array[wp.vec3],
    particle_torque: wp.array[wp.vec3],
    gravity: wp.vec3,
    dt: float,
    # outputs (v, omega updated in place)
    spheres: SphereArrays,
):
    """Second half kick with the forces of the new positions."""
    i = wp.tid()
    if spheres.alive[i] == 0:
        return
    half_kick(spheres, i, particle_f[i], particle_torque[i], gravity, dt)


def sphere_arrays(particles) -> SphereArrays:
    """The ``SphereArrays`` view of a ``hel_warp.parcels.particles.Particles`` (no copy)."""
    s = SphereArrays()
    s.x, s.v, s.omega = particles.x, particles.v, particles.omega
    s.radius, s.density, s.alive = particles.radius, particles.density, particles.alive
    return s


def launch_kick_drift(spheres: SphereArrays, force, torque, gravity, dt: float) -> None:
    wp.launch(kick_drift, dim=spheres.x.shape[0], device=spheres.x.device,
              inputs=[force, torque, gravity, dt], outputs=[spheres])


def launch_kick(spheres: SphereArrays, force, torque, gravity, dt: float) -> None:
    wp.launch(kick, dim=spheres.x.shape[0], device=spheres.x.device,
              inputs=[force, torque, gravity, dt], outputs=[spheres])


# ------------------------------------------------------------------------------------------ CFD-DEM: held fluid force

@wp.kernel
def held_fluid_acceleration(
    particle_v_start: wp.array(dtype=wp.vec3),
    particle_v_push: wp.array(dtype=wp.vec3),
    particle_alive: wp.array(dtype=wp.int32),
    dt: float,
    # outputs
    parcel_a_fluid: wp.array(dtype=wp.vec3),
):
    """a_fluid = (v after the fluid-only push - v at the start) / dt: drag, gravity, grad p' of eq. (4)."""
    i = wp.tid()
    if particle_alive[i] == 0:
        parcel_a_fluid[i] = wp.vec3(0.0)
        return
    parcel_a_fluid[i] = (particle_v_push[i] - particle_v_start[i]) / dt


@wp.kernel
def add_fluid_force(
    parcel_a_fluid: wp.array(dtype=wp.vec3),
    particle_radius: wp.array(dtype=wp.float32),
    particle_density: wp.array(dtype=wp.float32),
    # outputs
    particle_f: wp.array(dtype=wp.vec3),
):
    """F_i <- F_i + m_i a_fluid_i (m = rho 4/3 pi r^3, the DEM integrator's mass)."""
    i = wp.tid()
    m = sphere_mass(particle_radius[i], particle_density[i])
    particle_f[i] = particle_f[i] + m * parcel_a_fluid[i]


def launch_held_fluid_acceleration(v_start, v_push, alive, dt: float, a_fluid) -> None:
    wp.launch(held_fluid_acceleration, dim=v_start.shape[0], device=v_start.device,
              inputs=[v_start, v_push, alive, float(dt)], outputs=[a_fluid])


def launch_add_fluid_force(a_fluid, radius, density, force) -> None:
    wp.launch(add_fluid_force, dim=a_fluid.shape[0], device=a_fluid.device, inputs=[a_fluid, radius, density],
              outputs=[force])
