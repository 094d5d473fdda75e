"""Sphere-wall contacts: the plane walls of a box and a generic signed-distance (SDF) wall.

A wall is rigid and fixed. Sphere i touches a wall when its centre lies closer than its radius:
plane ``{y : (y - p) . n = 0}`` with unit normal n pointing into the domain, gap ``(x - p) . n``;
SDF wall with ``phi(x)`` > 0 in the domain, gap ``phi(x)`` and normal ``grad phi / |grad phi|``
(central differences of step ``h``). Overlap ``delta = r - gap``. The force is the same
Hertz-Mindlin law as between particles (``kernels/hertz.py``) with the wall terms of the
effective quantities vanishing (R* = r, m* = m; Johnson 1985, §4.2; E*, G* of the wall material
pair, built on the host), its shear history kept per particle and per wall. In the convention of
``kernels/hertz.py`` (normal from body 1 to body 2) the contact normal is ``-n``, the contact
point ``x - r n`` and its velocity ``v - r w x n``. These kernels *add* to the force and torque arrays written by
``kernels/contacts.py``; one thread per particle, no atomics.
"""

from __future__ import annotations

import warp as wp

from kernels.contacts import with_bodies
from kernels.hertz import ContactParams, contact_force, rolling_torque
from kernels.integrate import SphereArrays, sphere_mass
from kernels.sdf import SdfShapes, sdf_union, sdf_union_normal


@wp.func
def wall_contact(
    n: wp.vec3, gap: float, x_radius: float, mass: float, v: wp.vec3, omega: wp.vec3, shear: wp.vec3,
    params: ContactParams, dt: float,
):
    """Force, new shear and torque on a sphere at distance ``gap`` from a wall of inward normal ``n``."""
    overlap = x_radius - gap
    force = wp.vec3(0.0)
    torque = wp.vec3(0.0)
    new_shear = wp.vec3(0.0)
    if overlap > 0.0:
        v_rel = v - wp.cross(x_radius * omega, n)
        p = with_bodies(params, x_radius, mass)
        force, new_shear, fn = contact_force(-n, overlap, v_rel, shear, p, dt)
        torque = wp.cross(-x_radius * n, force)
        if p.rolling_friction > 0.0:
            torque = torque + rolling_torque(p, -n, omega, fn)
    return force, new_shear, torque


@wp.kernel
def plane_wall_forces(
    spheres: SphereArrays,
    wall_point: wp.array[wp.vec3],
    wall_normal: wp.array[wp.vec3],
    params: ContactParams,
    dt: float,
    # outputs (wall_shear (N, n_walls) updated in place; force and torque accumulated)
    wall_shear: wp.array2d[wp.vec3],
    particle_f: wp.array[wp.vec3],
    particle_torque: wp.array[wp.vec3],
):
    i = wp.tid()
    if spheres.alive[i] == 0:
        return
    x = spheres.x[i]
    r = spheres.radius[i]
    m = sphere_mass(r, spheres.density[i])
    f = wp.vec3(0.0)
    t = wp.vec3(0.0)
    touching = int(0)
    for w in range(wall_point.shape[0]):
        n = wall_normal[w]
        gap = wp.dot(x - wall_point[w], n)
        if gap < r:
            result = wall_contact(n, gap, r, m, spheres.v[i], spheres.omega[i], wall_shear[i, w], params, dt)
            f = f + result[0]
            wall_shear[i, w] = result[1]
            t = t + result[2]
            touching = 1
        else:
            wall_shear[i, w] = wp.vec3(0.0)  # the contact opened: forget its history
    if touching != 0:
        particle_f[i] = particle_f[i] + f
        particle_torque[i] = particle_torque[i] + t


def make_sdf_wall_kernel(sdf):
    """A force kernel for the wall ``phi = sdf(x)`` (a ``@wp.func`` vec3 -> float, m, > 0 in the domain).

    The returned kernel takes (spheres, params, dt, gradient_step,
    # outputs: wall_shear (N,), force, torque) and adds the wall force and torque.
    """

    @wp.kernel(module="unique")
    def sdf_wall_forces(
        spheres: SphereArrays,
        params: ContactParams,
        dt: float,
        gradient_step: float,
        # outputs
        wall_shear: wp.array[wp.vec3],
        particle_f: wp.array[wp.vec3],
        particle_torque: wp.array[wp.vec3],
    ):
        i = wp.tid()
        if spheres.alive[i] == 0:
            return
        x = spheres.x[i]
        r = spheres.radius[i]
        gap = sdf(x)
        if gap >= r:
            wall_shear[i] = wp.vec3(0.0)
            return
        h = gradient_step
        grad = wp.vec3(
            sdf(x + wp.vec3(h, 0.0, 0.0)) - sdf(x - wp.vec3(h, 0.0, 0.0)),
            sdf(x + wp.vec3(0.0, h, 0.0)) - sdf(x - wp.vec3(0.0, h, 0.0)),
            sdf(x + wp.vec3(0.0, 0.0, h)) - sdf(x - wp.vec3(0.0, 0.0, h)),
        )
        glen = wp.length(grad)
        if glen <= 0.0:
            return
        n = grad / glen
        m = sphere_mass(r, spheres.density[i])
        result = wall_contact(n, gap, r, m, spheres.v[i], spheres.omega[i], wall_shear[i], params, dt)
        wall_shear[i] = result[1]
        particle_f[i] = particle_f[i] + result[0]
        particle_torque[i] = particle_torque[i] + result[2]

    return sdf_wall_forces


def launch_plane_wall_forces(spheres: SphereArrays, wall_point, wall_normal, params: ContactParams, dt: float,
                             wall_shear, force, torque) -> None:
    wp.launch(plane_wall_forces, dim=spheres.x.shape[0], device=spheres.x.device,
              inputs=[spheres, wall_point, wall_normal, params, dt], outputs=[wall_shear, force, torque])


def launch_sdf_wall_forces(kernel, spheres: SphereArrays, params: ContactParams, dt: float, gradient_step: float,
                           wall_shear, force, torque) -> None:
    wp.launch(kernel, dim=spheres.x.shape[0], device=spheres.x.device,
              inputs=[spheres, params, dt, gradient_step], outputs=[wall_shear, force, torque])


# ------------------------------------------------------------------------------------------ flow-geometry (SDF) walls of the CFD-DEM

@wp.kernel
def geometry_wall_forces(
    spheres: SphereArrays,
    shapes: SdfShapes,
    params: ContactParams,
    dt: float,
    # outputs (wall_shear updated in place; force and torque accumulated)
    wall_shear: wp.array(dtype=wp.vec3),
    particle_f: wp.array(dtype=wp.vec3),
    particle_torque: wp.array(dtype=wp.vec3),
):
    """Hertz-Mindlin sphere-wall contact against the flow geometry's SDF (``kernels/sdf.py``, negative in
    the fluid): gap ``-sdf_union(x)``, inward normal ``-sdf_union_normal(x)``, the contact law of
    ``kernels/walls.py`` (``wall_contact``); one wall history per parcel, forgotten when the contact opens."""
    i = wp.tid()
    if spheres.alive[i] == 0:
        wall_shear[i] = wp.vec3(0.0)
        return
    x = spheres.x[i]
    r = spheres.radius[i]
    gap = -sdf_union(shapes, x)
    if gap >= r:
        wall_shear[i] = wp.vec3(0.0)
        return
    n = -sdf_union_normal(shapes, x)
    m = sphere_mass(r, spheres.density[i])
    result = wall_contact(n, gap, r, m, spheres.v[i], spheres.omega[i], wall_shear[i], params, dt)
    wall_shear[i] = result[1]
    particle_f[i] = particle_f[i] + result[0]
    particle_torque[i] = particle_torque[i] + result[2]


def launch_geometry_wall_forces(spheres: SphereArrays, shapes: SdfShapes, params: ContactParams, dt: float,
                                wall_shear, force, torque) -> None:
    """Add the SDF-geometry wall contact force and torque of every live sphere (``geometry_wall_forces``)."""
    wp.launch(geometry_wall_forces, dim=spheres.x.shape[0], device=spheres.x.device,
              inputs=[spheres, shapes, params, dt], outputs=[wall_shear, force, torque])
