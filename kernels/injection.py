"""Injection sites: a candidate position of a new parcel is blocked when a live parcel is too close.

``hel_warp.parcels.pool`` places volume-injected parcels only where no live parcel lies within
``(r_i + r_j)(1 + clearance)`` of the candidate (the overlap test of the HELSCM pair detection, one
thread per candidate on the hash grid of the pool), so an injection never starts an overlap.
"""

from __future__ import annotations

import warp as wp


@wp.kernel
def flag_blocked_sites(
    grid: wp.uint64,
    particle_x: wp.array(dtype=wp.vec3),
    particle_radius: wp.array(dtype=wp.float32),
    particle_alive: wp.array(dtype=wp.int32),
    max_radius: float,
    clearance: float,
    site_x: wp.array(dtype=wp.vec3),
    site_radius: wp.array(dtype=wp.float32),
    # outputs
    site_blocked: wp.array(dtype=wp.int32),
):
    """site_blocked[k] = 1 when a live parcel j has |x_k - x_j| < (r_k + r_j)(1 + clearance), else 0."""
    k = wp.tid()
    xk = site_x[k]
    rk = site_radius[k]
    blocked = int(0)
    for j in wp.hash_grid_query(grid, xk, (rk + max_radius) * (1.0 + clearance)):
        if particle_alive[j] != 0:
            cut = (rk + particle_radius[j]) * (1.0 + clearance)
            if wp.length_sq(particle_x[j] - xk) < cut * cut:
                blocked = 1
    site_blocked[k] = blocked


def launch_flag_blocked_sites(grid, particles, max_radius: float, clearance: float, site_x, site_radius,
                              site_blocked) -> None:
    """Flag the candidate sites that a live parcel of ``particles`` (hashed in ``grid``) overlaps."""
    wp.launch(flag_blocked_sites, dim=site_x.shape[0], device=site_x.device,
              inputs=[grid.id, particles.x, particles.radius, particles.alive, float(max_radius), float(clearance),
                      site_x, site_radius], outputs=[site_blocked])
