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


@wp.func
def sphere_mass(radius: float, density: float):
    """m = rho 4/3 pi r^3, kg."""
    return density * (4.0 / 3.0 * wp.pi) * radius * radius * radius


@wp.kernel
def kick_drift(
    particle_f: wp.array[wp.vec3],
    particle_torque: wp.array[wp.vec3],
    particle_radius: wp.array[wp.float32],
    particle_density: wp.array[wp.float32],
    particle_alive: wp.array[wp.int32],
    gravity: wp.vec3,
    dt: float,
    # outputs (updated in place)
    particle_x: wp.array[wp.vec3],
    particle_v: wp.array[wp.vec3],
    particle_omega: wp.array[wp.vec3],
):
    """Half kick with the forces of the current positions, then a full drift."""
    i = wp.tid()
    if particle_alive[i] == 0:
        return
    r = particle_radius[i]
    m = sphere_mass(r, particle_density[i])
    half_dt = 0.5 * dt
    v = particle_v[i] + (particle_f[i] / m + gravity) * half_dt
    particle_v[i] = v
    particle_omega[i] = particle_omega[i] + particle_torque[i] * (half_dt / (0.4 * m * r * r))
    particle_x[i] = particle_x[i] + v * dt


@wp.kernel
def kick(
    particle_f: wp.array[wp.vec3],
    particle_torque: wp.array[wp.vec3],
    particle_radius: wp.array[wp.float32],
    particle_density: wp.array[wp.float32],
    particle_alive: wp.array[wp.int32],
    gravity: wp.vec3,
    dt: float,
    # outputs (updated in place)
    particle_v: wp.array[wp.vec3],
    particle_omega: wp.array[wp.vec3],
):
    """Second half kick with the forces of the new positions."""
    i = wp.tid()
    if particle_alive[i] == 0:
        return
    r = particle_radius[i]
    m = sphere_mass(r, particle_density[i])
    half_dt = 0.5 * dt
    particle_v[i] = particle_v[i] + (particle_f[i] / m + gravity) * half_dt
    particle_omega[i] = particle_omega[i] + particle_torque[i] * (half_dt / (0.4 * m * r * r))


def launch_kick_drift(particles, force, torque, gravity, dt: float) -> None:
    wp.launch(kick_drift, dim=particles.count, device=particles.device,
              inputs=[force, torque, particles.radius, particles.density, particles.alive, gravity, dt],
              outputs=[particles.x, particles.v, particles.omega])


def launch_kick(particles, force, torque, gravity, dt: float) -> None:
    wp.launch(kick, dim=particles.count, device=particles.device,
              inputs=[force, torque, particles.radius, particles.density, particles.alive, gravity, dt],
              outputs=[particles.v, particles.omega])
