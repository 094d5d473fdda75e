"""KTGF collision closures of the HEL model (paper eqs. (5)-(8), Table 1) and the MP-PIC
collision acceleration.

Closures (e = e_ss, Theta the granular temperature, m^2/s^2; viscosities are the full
coefficients of sigma_s = -p_s I + mu_s (grad u + grad u^T) + (lambda_s - 2/3 mu_s) div(u) I,
i.e. Gidaspow's (1994) convention, equal to Fluent's eps_s * mu_s):

- radial distribution (Ogawa et al. 1980 / Lun et al. 1984, Fluent "lun-et-al"):
      g0 = [1 - (eps_s / eps_s,max)^(1/3)]^-1                      (infinite at packing)
- solids pressure (Lun et al. 1984):
      p_s = eps_s rho_s Theta + 2 rho_s (1 + e) eps_s^2 g0 Theta   (the paper's eq. (7) is garbled)
- granular shear viscosity (Gidaspow 1994, *Multiphase Flow and Fluidization*, ch. 9):
      mu_s = 4/5 eps_s^2 rho_s d g0 (1 + e) sqrt(Theta/pi)
           + 10 rho_s d sqrt(pi Theta) / (96 (1 + e) g0) [1 + 4/5 g0 eps_s (1 + e)]^2
- bulk viscosity (Lun et al. 1984):  lambda_s = 4/3 eps_s^2 rho_s d g0 (1 + e) sqrt(Theta/pi)
- frictional viscosity (Schaeffer 1987): mu_fr = p_s sin(phi) / (2 sqrt(I_2D)) for
  eps_s > eps_s,fric (0.61), zero below; frictional pressure "based-ktgf" = p_s.
- algebraic granular temperature: the paper's eq. (8) (Fluent's algebraic form, "neglecting
  convection and diffusion"; Gidaspow 1994, ch. 9) with the closures of Syamlal, Rogers & O'Brien
  (1993, MFIX ``calc_mu_s.f``):
      0 = (-p_s I + tau_s) : grad u - gamma - 3 K_sg Theta
        = -p_s trD + lambda_s trD^2 + 2 mu_s D:D - gamma - 3 K_sg Theta
  with p_s = K1 eps_s^2 Theta, lambda_s = K2 eps_s sqrt(Theta), mu_s = K3 eps_s sqrt(Theta),
  gamma = K4 eps_s^2 Theta^(3/2) = 12 (1 - e^2) g0 rho_s eps_s^2 Theta^(3/2) / (d sqrt(pi)),
  K1 = 2 (1 + e) rho_s g0,
  K3 = d rho_s / 2 {sqrt(pi) / (3 (3 - e)) [1/2 (3e + 1) + 0.4 (1 + e)(3e - 1) eps_s g0] + 8 eps_s g0 (1 + e) / (5 sqrt(pi))},
  K2 = 4 d rho_s (1 + e) eps_s g0 / (3 sqrt(pi)) - 2/3 K3,   K4 = 12 (1 - e^2) rho_s g0 / (d sqrt(pi)),
  K_sg the gas-solid exchange coefficient (kg/(m^3 s)) of the cell, = sum(beta V) / V_cell from the
  deposit's ``cell_drag_coeff``. With x = sqrt(Theta) > 0, dividing by eps_s x:
      A x^2 + B x - C = 0,  A = K4 eps_s,  B = K1 eps_s trD + 3 K_sg / eps_s,  C = K2 trD^2 + 2 K3 D:D,
  C >= 0 because D:D >= trD^2/3 (C >= 4 d rho_s (1+e) eps_s g0 trD^2 / (3 sqrt(pi))), so there is
  exactly one non-negative root, x = 2C / (B + sqrt(B^2 + 4AC)) for B >= 0 (no cancellation),
  (-B + sqrt(B^2 + 4AC)) / (2A) for B < 0. K_sg = 0 gives back the MFIX root
      sqrt(Theta) = [-K1 eps_s trD + sqrt(K1^2 eps_s^2 trD^2 + 4 K4 eps_s (K2 trD^2 + 2 K3 tr(D^2)))] / (2 K4 eps_s).
  The pressure work uses MFIX's p_s = K1 eps_s^2 Theta (as Syamlal et al.), not the kinetic part
  eps_s rho_s Theta of the Lun p_s below.
- solids velocity gradient for D: the solids phase (and its velocity) exists only in cells with
  eps_s >= eps_s_min; an empty cell's deposited velocity is a placeholder 0, not a solids velocity.
  Per axis: central difference when both neighbours hold solids, one-sided against the centre cell
  when only one does, zero when neither does (a lone parcel has no resolved solids strain).
- MP-PIC collision acceleration at a parcel (Snider 2001; Andrews & O'Rourke 1996):
      a_coll = -grad(p_s) / (eps_s rho_p)                        (eq. (5)-(6) with sigma_s = -p_s I)

Stability (the collision acceleration is explicit in the push, eq. (4)):
- what runs away (colliding-streams rig, 315 um, dt = 1e-3 s, h = 1 mm, unlimited term, measured): at the
  first step with solids strain (t = 3 ms) g0 <= 2.62 (eps_s <= 0.149: packing plays no part) and cells with
  eps_s >= 0.05 have Theta <= 12.7 m^2/s^2, but a near-empty fringe cell (eps_s = 4.8e-5) has Theta = 585:
  in the dilute limit the algebraic root tends to Theta = 2 K3 D:D / (K4 eps_s) (K3, K4 finite as eps_s -> 0),
  i.e. Theta ~ 1/eps_s. Its p_s ~ eps_s rho_s Theta stays finite, but the resulting |grad p_s| (1.55e6 Pa/m)
  divided by the small interpolated eps_s of fringe parcels gives |a_coll| dt = 46 m/s, a collision
  displacement |a_coll| dt^2 = 46 h in one step. The parcels overshoot the cell over which the gradient
  acts, create new strain, and the loop grows x3-x5 per step: |a| dt = 160, 725, 1850, 8540 m/s at 4-7 ms,
  max Theta 4e4 -> 1.1e8, max speed 915 m/s at 6 ms, 1e8 m/s at 12 ms, most parcels lost.
- treatment: the explicit particle-stress term is stable only while one step's collision velocity moves a
  parcel by less than the distance over which the resolved stress gradient acts (grad p_s is a central
  difference over <= 2 h, sampled with the cloud-in-cell kernel of support h; the analogue of the
  acoustic condition c_s dt < h for the granular sound speed c_s^2 = dp_s/d(eps_s) / rho_p). As in the
  MP-PIC particle-stress treatment of Snider (2001, J. Comput. Phys. 170:523-549) and O'Rourke & Snider
  (2010, Chem. Eng. Sci. 65:6014-6028) - a parcel is not moved further in one step than is needed to
  relieve the packing that pushes it - the collision acceleration of each parcel is limited in magnitude
  (direction kept) to
      |a_coll| <= h / dt^2        (|a_coll| dt^2 <= h: at most one cell of collision displacement per step).
  This is the only limit: no bound on Theta, p_s or g0. Where the explicit term already satisfies it the
  result is bit-identical (three-streams case: max |a_coll| dt^2 / h = 0.020, every output identical).
  With it the rig above stays bounded (max speed 37.5 m/s at 6 ms, 15.6 m/s at 20 ms, 263 of 12000 parcels
  through the outlets, check() clean; ``none``: 23.6 m/s at 6 ms, 15.3 at 20 ms, 387 removed). At dt = 1e-4 s
  (limit 10x looser per step) it is bounded too (no exponential growth, check() clean, max speed 55-67 m/s
  from 12 to 20 ms) but 1510 parcels exceed 20 m/s at 20 ms with nearly isotropic velocities and 981 leave:
  the near-empty fringe cells still hold the dilute-limit Theta ~ 1/eps_s, whose p_s kicks their few
  parcels every step. At dt = 7.14e-5 s it is stronger (max 74-90 m/s from 12 ms, 2231 parcels > 20 m/s and
  1614 removed at 20 ms, check() clean): the limit loosens as 1/dt^2, so it bounds the blow-up but does not
  remove this fringe heating. Its source is the closure's dilute limit (mean free path
  d / (6 sqrt(2) eps_s g0) >> h in those cells); OPEN: a treatment of Theta there or a fully implicit
  particle-stress solve (Snider 2001) is still needed for dt <= 1e-4 s.
  ``collision_acceleration(dt=None)`` keeps the unlimited term.

Cell-centred fields, uniform spacing h; derivatives by central differences (one-sided at the
grid boundary; the solids velocity gradient also one-sided / zero next to cells without solids).
"""

from __future__ import annotations

import warp as wp

from kernels.interp import CellGrid, cic_axis, cic_corner, cic_stencil, parcel_cell, parcel_stencil


@wp.func
def radial_distribution_lun(eps_s: float, eps_s_max: float):
    """g0 = 1 / (1 - (eps_s/eps_s_max)^(1/3)) (Ogawa/Lun); infinite at packing."""
    return 1.0 / (1.0 - wp.pow(eps_s / eps_s_max, 1.0 / 3.0))


@wp.func
def solids_pressure_lun(eps_s: float, rho_s: float, restitution: float, g0: float, theta: float):
    """p_s = eps_s rho_s Theta + 2 rho_s (1 + e) eps_s^2 g0 Theta (Lun et al. 1984), Pa."""
    return eps_s * rho_s * theta * (1.0 + 2.0 * (1.0 + restitution) * eps_s * g0)


@wp.func
def granular_viscosity_gidaspow(eps_s: float, rho_s: float, diameter: float, restitution: float, g0: float,
                                theta: float):
    """mu_s (Pa s), Gidaspow (1994): collisional 4/5 eps^2 rho d g0 (1+e) sqrt(Theta/pi) + kinetic part."""
    one_e = 1.0 + restitution
    collisional = 0.8 * eps_s * eps_s * rho_s * diameter * g0 * one_e * wp.sqrt(theta / wp.pi)
    bracket = 1.0 + 0.8 * g0 * eps_s * one_e
    kinetic = 10.0 * rho_s * diameter * wp.sqrt(wp.pi * theta) / (96.0 * one_e * g0) * bracket * bracket
    return collisional + kinetic


@wp.func
def bulk_viscosity_lun(eps_s: float, rho_s: float, diameter: float, restitution: float, g0: float, theta: float):
    """lambda_s = 4/3 eps_s^2 rho_s d g0 (1 + e) sqrt(Theta/pi) (Lun et al. 1984), Pa s."""
    return 4.0 / 3.0 * eps_s * eps_s * rho_s * diameter * g0 * (1.0 + restitution) * wp.sqrt(theta / wp.pi)


@wp.func
def schaeffer_viscosity(eps_s: float, eps_s_fric: float, p_s: float, friction_angle: float, i2d: float):
    """mu_fr = p_s sin(phi) / (2 sqrt(I_2D)) above the friction packing eps_s_fric, else 0 (Schaeffer 1987)."""
    if eps_s <= eps_s_fric or i2d <= 0.0:
        return 0.0
    return p_s * wp.sin(friction_angle) / (2.0 * wp.sqrt(i2d))


@wp.func
def second_invariant_deviatoric(strain_rate: wp.mat33):
    """I_2D = 1/6 [(D11-D22)^2 + (D22-D33)^2 + (D33-D11)^2] + D12^2 + D23^2 + D31^2."""
    d = strain_rate
    a = d[0, 0] - d[1, 1]
    b = d[1, 1] - d[2, 2]
    c = d[2, 2] - d[0, 0]
    return (a * a + b * b + c * c) / 6.0 + d[0, 1] * d[0, 1] + d[1, 2] * d[1, 2] + d[2, 0] * d[2, 0]


@wp.func
def mean_free_path_factor(eps_s: float, diameter: float, g0: float, length: float):
    """1 / (1 + lambda / L), lambda = d / (6 sqrt(2) eps_s g0) the mean free path (Chapman & Cowling; Hrenya &
    Sinclair 1997, AIChE J. 43:853, who limit the dilute granular viscosity by it); 1 when L <= 0 (off)."""
    if length <= 0.0:
        return 1.0
    return 1.0 / (1.0 + diameter / (6.0 * wp.sqrt(2.0) * eps_s * g0 * length))


@wp.func
def algebraic_theta(eps_s: float, rho_s: float, diameter: float, restitution: float, g0: float, tr_d: float,
                    tr_d2: float, k_sg: float, mfp_length: float):
    """Theta (m^2/s^2) zeroing production - dissipation - 3 K_sg Theta (paper eq. (8); closures of
    Syamlal et al. 1993 / MFIX calc_mu_s.f; see the module docstring for the quadratic in sqrt(Theta)).

    tr_d = trace(D), tr_d2 = D:D, D the solids strain-rate tensor (1/s); k_sg the gas-solid exchange
    coefficient, kg/(m^3 s) (0: the MFIX root). 0 where eps_s <= 0. ``mfp_length`` L > 0 multiplies the
    dilute (streaming) viscosity term of K3 by :func:`mean_free_path_factor` (0: the closure as published).
    """
    if eps_s <= 0.0:
        return 0.0
    e = restitution
    sqrt_pi = wp.sqrt(wp.pi)
    k1 = 2.0 * (1.0 + e) * rho_s * g0
    dilute = 0.5 * (3.0 * e + 1.0) * mean_free_path_factor(eps_s, diameter, g0, mfp_length)
    k3 = 0.5 * diameter * rho_s * (sqrt_pi / (3.0 * (3.0 - e)) * (dilute
                                   + 0.4 * (1.0 + e) * (3.0 * e - 1.0) * eps_s * g0)
                                   + 8.0 * eps_s * g0 * (1.0 + e) / (5.0 * sqrt_pi))
    k2 = 4.0 * diameter * rho_s * (1.0 + e) * eps_s * g0 / (3.0 * sqrt_pi) - 2.0 / 3.0 * k3
    k4 = 12.0 * (1.0 - e * e) * rho_s * g0 / (diameter * sqrt_pi)
    a = k4 * eps_s
    b = k1 * eps_s * tr_d + 3.0 * wp.max(k_sg, 0.0) / eps_s
    c = wp.max(k2 * tr_d * tr_d + 2.0 * k3 * tr_d2, 0.0)
    sq = wp.sqrt(b * b + 4.0 * a * c)
    root = 0.0
    if b >= 0.0:
        if c > 0.0:
            root = 2.0 * c / (b + sq)
    else:
        root = (sq - b) / (2.0 * a)
    return root * root


@wp.struct
class KtgfParams:
    """Table 1 constants. diameter m, density kg/m^3, friction_angle rad."""

    restitution: float
    """e_ss (0.9)."""
    packing: float
    """eps_s,max of g0 (0.63)."""
    friction_packing: float
    """eps_s above which Schaeffer friction acts (0.61)."""
    friction_angle: float
    """internal friction angle phi of Schaeffer's law, rad (30 deg)."""
    max_fraction_of_packing: float
    """eps_s used in g0 is capped at this fraction of packing (0.999) so g0 stays finite in overfull cells."""
    eps_s_min: float
    """below this solid fraction a cell carries no granular pressure and a parcel no collision force."""
    particle_diameter: float
    particle_density: float
    mfp_length: float
    """L of the mean-free-path limit of the dilute viscosity in the algebraic Theta, m (0: off, the published
    closure; the HEL strategy uses the cell size: no solids shear is resolved below it)."""


@wp.func
def _index_pair(i: int, n: int, periodic: int):
    """Neighbours of cell i for a central difference and the number of spacings between them
    (wrapped when periodic; one-sided at a bounded edge; span 0 when n == 1)."""
    if periodic != 0 and n >= 3:
        return (i - 1 + n) % n, (i + 1) % n, 2
    lo = wp.max(i - 1, 0)
    hi = wp.min(i + 1, n - 1)
    return lo, hi, hi - lo


@wp.func
def _solids_difference(u_c: wp.vec3, u_lo: wp.vec3, u_hi: wp.vec3, lo_ok: bool, hi_ok: bool, span: int,
                       spacing: float):
    """d u / d x along one axis from the neighbours that hold solids: central (over ``span`` spacings)
    when both do, one-sided against the centre when one does, zero when neither does."""
    if lo_ok and hi_ok:
        return (u_hi - u_lo) / (float(span) * spacing)
    if hi_ok:
        return (u_hi - u_c) / spacing
    if lo_ok:
        return (u_c - u_lo) / spacing
    return wp.vec3(0.0)


@wp.kernel
def ktgf_cells_kernel(
    params: KtgfParams,
    spacing: float,
    periodic: wp.vec3i,
    cell_eps_s: wp.array3d(dtype=float),
    cell_solid_velocity: wp.array3d(dtype=wp.vec3),
    cell_drag_coeff: wp.array3d(dtype=wp.float64),
    # outputs
    cell_g0: wp.array3d(dtype=float),
    cell_theta: wp.array3d(dtype=float),
    cell_p_s: wp.array3d(dtype=float),
    cell_mu_s: wp.array3d(dtype=float),
    cell_mu_fric: wp.array3d(dtype=float),
):
    i, j, k = wp.tid()
    nx = cell_eps_s.shape[0]
    ny = cell_eps_s.shape[1]
    nz = cell_eps_s.shape[2]
    eps = wp.min(cell_eps_s[i, j, k], params.max_fraction_of_packing * params.packing)
    if eps < params.eps_s_min:
        cell_g0[i, j, k] = 1.0
        cell_theta[i, j, k] = 0.0
        cell_p_s[i, j, k] = 0.0
        cell_mu_s[i, j, k] = 0.0
        cell_mu_fric[i, j, k] = 0.0
        return
    # velocity gradient G[a, b] = d u_a / d x_b, differences only between cells holding solids
    il, ih, si = _index_pair(i, nx, periodic[0])
    jl, jh, sj = _index_pair(j, ny, periodic[1])
    kl, kh, sk = _index_pair(k, nz, periodic[2])
    u_c = cell_solid_velocity[i, j, k]
    dudx = _solids_difference(u_c, cell_solid_velocity[il, j, k], cell_solid_velocity[ih, j, k],
                              il != i and cell_eps_s[il, j, k] >= params.eps_s_min,
                              ih != i and cell_eps_s[ih, j, k] >= params.eps_s_min, si, spacing)
    dudy = _solids_difference(u_c, cell_solid_velocity[i, jl, k], cell_solid_velocity[i, jh, k],
                              jl != j and cell_eps_s[i, jl, k] >= params.eps_s_min,
                              jh != j and cell_eps_s[i, jh, k] >= params.eps_s_min, sj, spacing)
    dudz = _solids_difference(u_c, cell_solid_velocity[i, j, kl], cell_solid_velocity[i, j, kh],
                              kl != k and cell_eps_s[i, j, kl] >= params.eps_s_min,
                              kh != k and cell_eps_s[i, j, kh] >= params.eps_s_min, sk, spacing)
    grad = wp.mat33(dudx[0], dudy[0], dudz[0], dudx[1], dudy[1], dudz[1], dudx[2], dudy[2], dudz[2])
    strain = 0.5 * (grad + wp.transpose(grad))
    tr_d = wp.trace(strain)
    tr_d2 = wp.ddot(strain, strain)
    g0 = radial_distribution_lun(eps, params.packing)
    k_sg = float(cell_drag_coeff[i, j, k]) / (spacing * spacing * spacing)  # sum beta V / V_cell
    theta = algebraic_theta(eps, params.particle_density, params.particle_diameter, params.restitution, g0,
                            tr_d, tr_d2, k_sg, params.mfp_length)
    p_s = solids_pressure_lun(eps, params.particle_density, params.restitution, g0, theta)
    cell_g0[i, j, k] = g0
    cell_theta[i, j, k] = theta
    cell_p_s[i, j, k] = p_s
    cell_mu_s[i, j, k] = granular_viscosity_gidaspow(eps, params.particle_density, params.particle_diameter,
                                                     params.restitution, g0, theta)
    cell_mu_fric[i, j, k] = schaeffer_viscosity(eps, params.friction_packing, p_s, params.friction_angle,
                                                second_invariant_deviatoric(strain))


@wp.kernel
def gradient_kernel(
    spacing: float,
    periodic: wp.vec3i,
    cell_field: wp.array3d(dtype=float),
    # outputs
    cell_gradient: wp.array3d(dtype=wp.vec3),
):
    i, j, k = wp.tid()
    il, ih, si = _index_pair(i, cell_field.shape[0], periodic[0])
    jl, jh, sj = _index_pair(j, cell_field.shape[1], periodic[1])
    kl, kh, sk = _index_pair(k, cell_field.shape[2], periodic[2])
    g = wp.vec3(0.0)
    if si > 0:
        g[0] = (cell_field[ih, j, k] - cell_field[il, j, k]) / (float(si) * spacing)
    if sj > 0:
        g[1] = (cell_field[i, jh, k] - cell_field[i, jl, k]) / (float(sj) * spacing)
    if sk > 0:
        g[2] = (cell_field[i, j, kh] - cell_field[i, j, kl]) / (float(sk) * spacing)
    cell_gradient[i, j, k] = g


@wp.kernel
def collision_acceleration_kernel(
    grid: CellGrid,
    eps_s_min: float,
    max_acceleration: float,
    accumulate: int,
    particle_x: wp.array(dtype=wp.vec3),
    particle_density: wp.array(dtype=float),
    cell_grad_p_s: wp.array3d(dtype=wp.vec3),
    cell_eps_s: wp.array3d(dtype=float),
    # outputs
    parcel_a_coll: wp.array(dtype=wp.vec3),
):
    """a_coll = -grad(p_s) / (eps_s rho_p), both interpolated with the cloud-in-cell weights; its magnitude
    limited to ``max_acceleration`` = h / dt^2 (the step moves a parcel at most one cell, module docstring)
    when ``max_acceleration`` > 0. ``accumulate`` != 0 adds it to ``parcel_a_coll`` instead of writing it (a
    second stress on top of a collision model's acceleration)."""
    tid = wp.tid()
    base, frac = cic_stencil(grid, particle_x[tid])
    grad = wp.vec3d(0.0, 0.0, 0.0)
    eps = wp.float64(0.0)
    for corner in range(8):
        idx, w = cic_corner(grid, base, frac, corner)
        g = cell_grad_p_s[idx[0], idx[1], idx[2]]
        grad = grad + w * wp.vec3d(wp.float64(g[0]), wp.float64(g[1]), wp.float64(g[2]))
        eps = eps + w * wp.float64(cell_eps_s[idx[0], idx[1], idx[2]])
    a = wp.vec3(0.0)
    if float(eps) >= eps_s_min:
        s = -1.0 / (float(eps) * particle_density[tid])
        a = wp.vec3(s * float(grad[0]), s * float(grad[1]), s * float(grad[2]))
        mag = wp.length(a)
        if max_acceleration > 0.0 and mag > max_acceleration:
            a = a * (max_acceleration / mag)
    if accumulate != 0:
        parcel_a_coll[tid] = parcel_a_coll[tid] + a
    else:
        parcel_a_coll[tid] = a


@wp.kernel
def closures_kernel(
    params: KtgfParams,
    eps_s: wp.array(dtype=float),
    theta: wp.array(dtype=float),
    tr_d: wp.array(dtype=float),
    tr_d2: wp.array(dtype=float),
    i2d: wp.array(dtype=float),
    k_sg: wp.array(dtype=float),
    # outputs: rows g0, algebraic theta (from tr_d, tr_d2, k_sg), then at the given theta: p_s, mu_s, lambda_s, mu_fric
    out: wp.array2d(dtype=float),
):
    """Point evaluation of the closures (tests, diagnostics)."""
    tid = wp.tid()
    eps = eps_s[tid]
    th = theta[tid]
    g0 = radial_distribution_lun(eps, params.packing)
    out[0, tid] = g0
    out[1, tid] = algebraic_theta(eps, params.particle_density, params.particle_diameter, params.restitution, g0,
                                  tr_d[tid], tr_d2[tid], k_sg[tid], params.mfp_length)
    p_s = solids_pressure_lun(eps, params.particle_density, params.restitution, g0, th)
    out[2, tid] = p_s
    out[3, tid] = granular_viscosity_gidaspow(eps, params.particle_density, params.particle_diameter,
                                              params.restitution, g0, th)
    out[4, tid] = bulk_viscosity_lun(eps, params.particle_density, params.particle_diameter, params.restitution,
                                     g0, th)
    out[5, tid] = schaeffer_viscosity(eps, params.friction_packing, p_s, params.friction_angle, i2d[tid])


# ---------------------------------------------------------------- launch wrappers

def make_ktgf_params(*, particle_diameter: float, particle_density: float, restitution: float = 0.9,
                     packing: float = 0.63, friction_packing: float = 0.61, friction_angle_deg: float = 30.0,
                     max_fraction_of_packing: float = 0.999, eps_s_min: float = 1e-8,
                     mfp_length: float = 0.0) -> KtgfParams:
    """``KtgfParams`` with Table 1 defaults (e_ss 0.9, packing 0.63, friction packing 0.61)."""
    import math

    p = KtgfParams()
    p.restitution = float(restitution)
    p.packing = float(packing)
    p.friction_packing = float(friction_packing)
    p.friction_angle = math.radians(friction_angle_deg)
    p.max_fraction_of_packing = float(max_fraction_of_packing)
    p.eps_s_min = float(eps_s_min)
    p.particle_diameter = float(particle_diameter)
    p.particle_density = float(particle_density)
    p.mfp_length = float(mfp_length)
    return p


def ktgf_cells(params: KtgfParams, spacing: float, cell_eps_s, cell_solid_velocity, *, cell_g0, cell_theta,
               cell_p_s, cell_mu_s, cell_mu_fric, periodic=(False, False, False), cell_drag_coeff=None):
    """g0, algebraic Theta, p_s, mu_s and Schaeffer mu_fr in every cell.

    ``cell_drag_coeff``: float64 sum of beta V per cell (kg/s, the deposit's), giving the exchange
    term 3 K_sg Theta of eq. (8) with K_sg = cell_drag_coeff / h^3; None = no gas-solid exchange."""
    if cell_drag_coeff is None:
        cell_drag_coeff = wp.zeros(cell_eps_s.shape, dtype=wp.float64, device=cell_eps_s.device)
    wp.launch(ktgf_cells_kernel, dim=cell_eps_s.shape, device=cell_eps_s.device,
              inputs=[params, float(spacing), wp.vec3i(*[int(bool(p)) for p in periodic]), cell_eps_s,
                      cell_solid_velocity, cell_drag_coeff],
              outputs=[cell_g0, cell_theta, cell_p_s, cell_mu_s, cell_mu_fric])


@wp.func
def packing_stress(eps_s: float, p_solid: float, beta: float, packed: float, onset: float, eps: float,
                   knee: float, knee_stress: float, stiffness: float):
    """tau = p_solid max(eps_s - onset, 0)^beta / max(packed - eps_s, eps (1 - eps_s)), Pa, continued along its
    tangent ``knee_stress`` + ``stiffness`` (eps_s - ``knee``) above ``knee`` when ``stiffness`` > 0.

    ``onset`` = 0: Harris & Crighton (1994), as Snider 2001's MP-PIC particle normal stress and OpenFOAM's
    ``HarrisCrighton``. ``onset`` > 0: no stress below it, the threshold of Johnson & Jackson's (1987) frictional
    pressure Fr (eps_s - eps_min)^n / (eps_max - eps_s)^p with p = 1: parcels looser than the onset have no
    enduring contacts. The tangent caps d tau / d eps_s, the stiffness an explicit step can carry
    (``hel_warp.hel.PackingStress``)."""
    e = wp.clamp(eps_s, 0.0, 0.999999)
    if stiffness > 0.0 and e > knee:
        return knee_stress + stiffness * (e - knee)
    return p_solid * wp.pow(wp.max(e - onset, 0.0), beta) / wp.max(packed - e, eps * (1.0 - e))


@wp.kernel
def packing_pressure_kernel(
    cell_eps_s: wp.array3d(dtype=float),
    p_solid: float,
    beta: float,
    packed: float,
    onset: float,
    eps: float,
    knee: float,
    knee_stress: float,
    stiffness: float,
    # outputs
    cell_p: wp.array3d(dtype=float),
):
    """:func:`packing_stress` of each cell's solids fraction."""
    i, j, k = wp.tid()
    cell_p[i, j, k] = packing_stress(cell_eps_s[i, j, k], p_solid, beta, packed, onset, eps, knee, knee_stress,
                                     stiffness)


@wp.kernel
def contact_damping_kernel(
    grid: CellGrid,
    onset: float,
    ramp: float,
    damping: float,
    particle_x: wp.array(dtype=wp.vec3),
    particle_weight: wp.array(dtype=float),
    particle_alive: wp.array(dtype=wp.int32),
    cell_eps_s: wp.array3d(dtype=float),
    cell_solid_velocity: wp.array3d(dtype=wp.vec3),
    # in/out
    particle_v: wp.array(dtype=wp.vec3),
):
    """v_i += sum_c w_ic f_c (u_s,c - v_i), f_c = ``damping`` clamp((eps_s,c - ``onset``) / ``ramp``, 0, 1): the
    parcels of a packed cell relax towards its mass-averaged solids velocity u_s,c (O'Rourke & Snider 2010's
    collision damping, complete where contacts endure). With the deposit's weights w_ic and u_s,c = P_c / M_c of the
    same velocities, sum_i m_i dv_i = sum_c f_c (M_c u_s,c - P_c) = 0: momentum exact; kinetic energy only falls."""
    tid = wp.tid()
    if particle_alive[tid] == 0:
        return
    v = particle_v[tid]
    base, frac, kw, b, norm = parcel_stencil(grid, particle_x[tid], particle_weight[tid], tid)
    dv = wp.vec3(0.0)
    for corner in range(8 * kw * kw * kw):
        idx, w = parcel_cell(grid, base, frac, kw, b, norm, corner)
        f = damping * wp.clamp((cell_eps_s[idx[0], idx[1], idx[2]] - onset) / ramp, 0.0, 1.0)
        dv = dv + (float(w) * f) * (cell_solid_velocity[idx[0], idx[1], idx[2]] - v)
    particle_v[tid] = v + dv


def contact_damping(grid: CellGrid, particles, cell_eps_s, cell_solid_velocity, *, onset: float, ramp: float,
                    damping: float) -> None:
    """:func:`contact_damping_kernel` on ``particles.v`` (``grid``: the deposit's ``CellGrid``, so its weights)."""
    wp.launch(contact_damping_kernel, dim=particles.x.shape[0], device=particles.x.device,
              inputs=[grid, float(onset), float(ramp), float(damping), particles.x, particles.weight, particles.alive,
                      cell_eps_s, cell_solid_velocity], outputs=[particles.v])


@wp.func
def _axis_cell(axis: int, i: int, jb: int, kc: int):
    """The cell with index ``i`` along ``axis`` and ``jb``, ``kc`` along the next two axes (cyclic)."""
    if axis == 0:
        return wp.vec3i(i, jb, kc)
    if axis == 1:
        return wp.vec3i(kc, i, jb)
    return wp.vec3i(jb, kc, i)


@wp.func
def _face_acceleration(grid: CellGrid, axis: int, lo: int, jb: int, kc: int, eps_s_min: float, rho_p: float,
                       cell_tau: wp.array3d(dtype=float), cell_eps_s: wp.array3d(dtype=float)):
    """-(tau_hi - tau_lo) / (h eps_face rho_p) on the face between cells ``lo`` and ``lo + 1`` along ``axis``
    (eps_face the mean of the two cells' eps_s); 0 on a boundary face (the wall's reaction is the reflection)."""
    n = grid.shape[axis]
    hi = lo + 1
    if grid.periodic[axis] != 0:
        lo = (lo + n) % n
        hi = hi % n
    elif lo < 0 or hi >= n:
        return 0.0
    a = _axis_cell(axis, lo, jb, kc)
    b = _axis_cell(axis, hi, jb, kc)
    eps = 0.5 * (cell_eps_s[a[0], a[1], a[2]] + cell_eps_s[b[0], b[1], b[2]])
    if eps < eps_s_min:
        return 0.0
    return -(cell_tau[b[0], b[1], b[2]] - cell_tau[a[0], a[1], a[2]]) / (float(grid.spacing) * eps * rho_p)


@wp.kernel
def face_stress_acceleration_kernel(
    grid: CellGrid,
    eps_s_min: float,
    max_acceleration: float,
    particle_x: wp.array(dtype=wp.vec3),
    particle_density: wp.array(dtype=float),
    particle_alive: wp.array(dtype=wp.int32),
    cell_tau: wp.array3d(dtype=float),
    cell_eps_s: wp.array3d(dtype=float),
    # outputs (added to)
    parcel_a_coll: wp.array(dtype=wp.vec3),
):
    """a_coll += -grad tau / (eps_s rho_p) with the gradient on the cell faces, (tau_{i+1} - tau_i) / h, each face's
    acceleration interpolated to the parcel linearly along its axis and bilinearly across (the MAC layout of the gas
    velocity). A cell-centred difference over 2 h leaves the odd-even pattern of tau without force: a packed bed
    then keeps a stress rising towards its surface that presses it onto the distributor (0.45 -> 0.5 m/s: 208 Pa
    across a bed of 189 Pa, measured). Boundary faces carry none (walls react by reflection). |a| is limited to
    ``max_acceleration`` (> 0) as ``collision_acceleration_kernel``'s."""
    tid = wp.tid()
    if particle_alive[tid] == 0:
        return
    x = particle_x[tid]
    rho_p = particle_density[tid]
    a = wp.vec3(0.0)
    for axis in range(3):
        b = (axis + 1) % 3
        c = (axis + 2) % 3
        u = (wp.float64(x[axis]) - grid.origin[axis]) / grid.spacing
        n = grid.shape[axis]
        i = wp.clamp(int(wp.floor(u)), 0, n - 1)
        f = float(wp.clamp(u - wp.float64(i), wp.float64(0.0), wp.float64(1.0)))
        jb, fb = cic_axis(wp.float64(x[b]), grid.origin[b], grid.spacing, grid.shape[b], grid.periodic[b])
        kc, fc = cic_axis(wp.float64(x[c]), grid.origin[c], grid.spacing, grid.shape[c], grid.periodic[c])
        total = float(0.0)
        for corner in range(4):
            db = corner & 1
            dc = corner >> 1
            wb = float(fb) if db == 1 else 1.0 - float(fb)
            wc = float(fc) if dc == 1 else 1.0 - float(fc)
            j = jb + db
            k = kc + dc
            if grid.periodic[b] != 0:
                j = (j + grid.shape[b]) % grid.shape[b]
            if grid.periodic[c] != 0:
                k = (k + grid.shape[c]) % grid.shape[c]
            j = wp.min(j, grid.shape[b] - 1)
            k = wp.min(k, grid.shape[c] - 1)
            lower = _face_acceleration(grid, axis, i - 1, j, k, eps_s_min, rho_p, cell_tau, cell_eps_s)
            upper = _face_acceleration(grid, axis, i, j, k, eps_s_min, rho_p, cell_tau, cell_eps_s)
            total = total + wb * wc * ((1.0 - f) * lower + f * upper)
        a[axis] = total
    mag = wp.length(a)
    if max_acceleration > 0.0 and mag > max_acceleration:
        a = a * (max_acceleration / mag)
    parcel_a_coll[tid] = parcel_a_coll[tid] + a


def face_stress_acceleration(grid: CellGrid, eps_s_min: float, particles, cell_tau, cell_eps_s, parcel_a_coll, *,
                             dt: float | None = None) -> None:
    """:func:`face_stress_acceleration_kernel` (``dt``: the HEL step, |a| <= h / dt^2; None: unlimited)."""
    max_acceleration = 0.0 if dt is None else float(grid.spacing) / float(dt) ** 2
    wp.launch(face_stress_acceleration_kernel, dim=particles.x.shape[0], device=particles.x.device,
              inputs=[grid, float(eps_s_min), max_acceleration, particles.x, particles.density, particles.alive,
                      cell_tau, cell_eps_s], outputs=[parcel_a_coll])


def packing_pressure(cell_eps_s, cell_p, *, p_solid: float, beta: float, packed: float, eps: float,
                     onset: float = 0.0, knee: float = 1.0, knee_stress: float = 0.0, stiffness: float = 0.0) -> None:
    """The MP-PIC packing stress of each cell (:func:`packing_stress`), Pa, into ``cell_p``."""
    wp.launch(packing_pressure_kernel, dim=cell_eps_s.shape, device=cell_eps_s.device,
              inputs=[cell_eps_s, float(p_solid), float(beta), float(packed), float(onset), float(eps), float(knee),
                      float(knee_stress), float(stiffness)],
              outputs=[cell_p])


def cell_gradient(spacing: float, cell_field, cell_gradient_out, periodic=(False, False, False)):
    """Central-difference gradient of a float32 cell field (wrapped along periodic axes)."""
    wp.launch(gradient_kernel, dim=cell_field.shape, device=cell_field.device,
              inputs=[float(spacing), wp.vec3i(*[int(bool(p)) for p in periodic]), cell_field],
              outputs=[cell_gradient_out])


def collision_acceleration(grid: CellGrid, eps_s_min: float, particle_x, particle_density, cell_grad_p_s,
                           cell_eps_s, parcel_a_coll, *, dt: float | None = None, accumulate: bool = False):
    """-grad(p_s)/(eps_s rho_p) at each parcel (Snider 2001).

    ``dt`` (s): the HEL step; given, |a_coll| is limited to h / dt^2 so that the collision velocity of one
    step, |a_coll| dt, moves a parcel at most one cell h, the distance over which the resolved grad p_s
    acts (module docstring, "Stability"). None: the unlimited explicit term. ``accumulate``: add to
    ``parcel_a_coll`` (limited on its own) instead of overwriting it."""
    max_acceleration = 0.0 if dt is None else float(grid.spacing) / float(dt) ** 2
    wp.launch(collision_acceleration_kernel, dim=particle_x.shape[0], device=particle_x.device,
              inputs=[grid, float(eps_s_min), max_acceleration, int(bool(accumulate)), particle_x, particle_density,
                      cell_grad_p_s, cell_eps_s],
              outputs=[parcel_a_coll])


def eval_closures(params: KtgfParams, eps_s, theta, tr_d, tr_d2, i2d, out, k_sg=None):
    """Rows of ``out`` (6, n): g0, algebraic Theta(tr_d, tr_d2, k_sg), and at the given ``theta``: p_s, mu_s,
    lambda_s, Schaeffer mu_fric(i2d). ``k_sg``: gas-solid exchange coefficient, kg/(m^3 s) (None = 0)."""
    if k_sg is None:
        k_sg = wp.zeros(eps_s.shape[0], dtype=float, device=eps_s.device)
    wp.launch(closures_kernel, dim=eps_s.shape[0], device=eps_s.device,
              inputs=[params, eps_s, theta, tr_d, tr_d2, i2d, k_sg], outputs=[out])
