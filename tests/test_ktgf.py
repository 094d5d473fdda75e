"""KTGF closures (Table 1) against values worked out by hand from the published formulas, their limits,
the algebraic granular temperature as the root of the local energy balance of eq. (8) (with the
gas-solid exchange 3 K_sg Theta), the solids strain taken only between cells holding solids, and the
MP-PIC collision acceleration -grad(p_s)/(eps_s rho_p)."""

import math

import numpy as np
import pytest
import warp as wp

from kernels import ktgf

RHO_S, D, E, EPS_MAX = 1000.0, 315e-6, 0.9, 0.63


def closures(eps_s, theta=0.01, tr_d=0.0, tr_d2=0.0, i2d=0.0, k_sg=0.0, mfp_length=0.0):
    """Evaluate the kernel-side closures at points; returns (6, n) float64 rows (see eval_closures)."""
    eps_s = np.atleast_1d(np.asarray(eps_s, np.float32))
    n = eps_s.size

    def arr(v):
        return wp.array(np.broadcast_to(np.asarray(v, np.float32), (n,)).copy(), dtype=float)

    out = wp.zeros((6, n), dtype=float)
    params = ktgf.make_ktgf_params(particle_diameter=D, particle_density=RHO_S, restitution=E, packing=EPS_MAX,
                                   mfp_length=mfp_length)
    ktgf.eval_closures(params, arr(eps_s), arr(theta), arr(tr_d), arr(tr_d2), arr(i2d), out, k_sg=arr(k_sg))
    return out.numpy().astype(np.float64)


def test_closures_match_hand_computation():
    # eps_s = 0.3, rho_s = 1000, d = 315e-6 m, e = 0.9, eps_max = 0.63, Theta = 0.01 m^2/s^2.
    # g0 = 1/(1 - (0.3/0.63)^(1/3)) = 1/(1 - 0.780897) = 4.564057          (Ogawa / Lun)
    # p_s = 0.3*1000*0.01 + 2*1000*1.9*0.09*4.564057*0.01 = 3.0 + 15.609073 = 18.609073 Pa   (Lun 1984)
    # mu_col = 0.8*0.09*1000*315e-6*4.564057*1.9*sqrt(0.01/pi) = 0.0110962 Pa s
    # mu_kin = 10*1000*315e-6*sqrt(0.01 pi)/(96*1.9*4.564057)*(1 + 0.8*4.564057*0.3*1.9)^2 = 0.00636725
    # mu_s = 0.0174634 Pa s                                                    (Gidaspow 1994)
    # lambda_s = 4/3*0.09*1000*315e-6*4.564057*1.9*sqrt(0.01/pi) = 0.0184936 Pa s   (Lun 1984)
    g0, _, p_s, mu_s, lam, mu_fr = closures(0.3, theta=0.01)[:, 0]
    assert g0 == pytest.approx(4.564057, rel=2e-6)
    assert p_s == pytest.approx(18.609073, rel=1e-5)
    assert mu_s == pytest.approx(0.0174634, rel=1e-5)
    assert lam == pytest.approx(0.0184936, rel=1e-5)
    assert mu_fr == 0.0  # below the friction packing 0.61


def test_algebraic_theta_simple_shear_hand_value():
    # Simple shear du_x/dy = 10 1/s: D_xy = D_yx = 5, tr D = 0, D:D = 50. Then the MFIX root reduces to
    # Theta = 2 K3 D:D / (K4 eps_s), with (eps_s = 0.3, g0 = 4.564057)
    # K3 = d rho/2 {sqrt(pi)/(3(3-e)) [ (3e+1)/2 + 0.4(1+e)(3e-1) eps g0 ] + 8 eps g0 (1+e)/(5 sqrt(pi))} = 0.530236
    # K4 = 12 (1-e^2) rho g0/(d sqrt(pi)) = 1.8638046e7
    # Theta = 2*0.530236*50/(1.8638046e7*0.3) = 9.48304e-6 m^2/s^2
    theta = closures(0.3, tr_d=0.0, tr_d2=50.0)[1, 0]
    assert theta == pytest.approx(9.48304e-6, rel=1e-5)


def test_algebraic_theta_with_gas_exchange_hand_value():
    # Same shear and eps_s, now with K_sg = 3000 kg/(m^3 s). Eq. (8) divided by eps_s sqrt(Theta) = x:
    # A x^2 + B x - C = 0, A = K4 eps_s = 5.591414e6, B = K1 eps_s trD + 3 K_sg/eps_s = 0 + 3e4,
    # C = K2 trD^2 + 2 K3 D:D = 2*0.530236*50 = 53.02360;
    # B^2 + 4AC = 9e8 + 1.185908e9 = 2.085908e9, sqrt = 45671.74;
    # x = 2C/(B + sqrt) = 106.0472/75671.74 = 1.401411e-3, Theta = 1.963953e-6 m^2/s^2 (4.8x below the
    # 9.48304e-6 without exchange).
    theta = closures(0.3, tr_d=0.0, tr_d2=50.0, k_sg=3000.0)[1, 0]
    assert theta == pytest.approx(1.963953e-6, rel=1e-5)
    # no strain: no production, Theta = 0 whatever the exchange
    assert closures(0.3, tr_d=0.0, tr_d2=0.0, k_sg=3000.0)[1, 0] == 0.0


def test_mean_free_path_limit_keeps_dilute_theta_finite():
    # Simple shear D:D = 50, K_sg = 0: Theta = 2 K3 D:D / (K4 eps_s). As published, K3 -> its dilute term
    # d rho sqrt(pi) (3e+1) / (12 (3-e)) as eps_s -> 0, so Theta ~ 1/eps_s. With the mean-free-path limit
    # (Hrenya & Sinclair 1997) that term carries 1/(1 + lambda/L), lambda = d/(6 sqrt(2) eps_s g0) -> L/lambda,
    # and Theta tends to (g0 -> 1)
    #   2 D:D d sqrt(pi) / (12 (1-e^2)) * [sqrt(2 pi) (3e+1) L / (2 (3-e))
    #                                      + d/2 (sqrt(pi) 0.4 (1+e)(3e-1) / (3 (3-e)) + 8 (1+e) / (5 sqrt(pi)))].
    L, dd = 1e-3, 50.0
    sp = math.sqrt(math.pi)
    limit = 2 * dd * D * sp / (12 * (1 - E**2)) * (math.sqrt(2 * math.pi) * (3 * E + 1) * L / (2 * (3 - E))
                                                  + D / 2 * (sp * 0.4 * (1 + E) * (3 * E - 1) / (3 * (3 - E))
                                                             + 8 * (1 + E) / (5 * sp)))
    eps = np.array([1e-6, 1e-5, 1e-4])
    limited = closures(eps, tr_d2=dd, mfp_length=L)[1]
    assert limited[0] == pytest.approx(limit, rel=1e-3)
    assert np.all(limited <= limit * (1 + 1e-3))
    published = closures(eps, tr_d2=dd)[1]
    # ~1/eps_s without the limit (g0 = 1.057 at eps_s = 1e-4 and 1.012 at 1e-6 make it 104)
    assert published[0] / published[2] == pytest.approx(100.0, rel=0.06)
    # dense cells: lambda << L, the limit changes Theta by about lambda/L (eps_s = 0.3: lambda = 16 um, 1.6 %)
    dense = closures(0.3, tr_d2=dd, mfp_length=L)[1, 0]
    assert dense < 9.48304e-6 and dense == pytest.approx(9.48304e-6, rel=0.02)


@pytest.mark.parametrize("eps_s,tr_d,tr_d2,k_sg", [(0.05, 0.0, 200.0, 0.0), (0.3, -4.0, 60.0, 0.0),
                                                   (0.3, 3.0, 40.0, 0.0), (0.55, -1.0, 5.0, 0.0),
                                                   (0.001, 0.5, 800.0, 0.0), (0.016, 0.0, 2.0e6, 210.0),
                                                   (0.016, -800.0, 1.0e6, 210.0), (0.3, 3.0, 40.0, 5.0e4),
                                                   (0.001, 0.5, 800.0, 13.0)])
def test_algebraic_theta_zeroes_energy_balance(eps_s, tr_d, tr_d2, k_sg):
    # Eq. (8) with Syamlal et al. (1993) closures: 0 = -p_s trD + lambda_s trD^2 + 2 mu_s D:D - gamma - 3 K_sg Theta
    # with p_s = K1 eps^2 Theta, lambda_s = K2 eps sqrt(Theta), mu_s = K3 eps sqrt(Theta),
    # gamma = K4 eps^2 Theta^1.5 (written here again).
    theta = closures(eps_s, tr_d=tr_d, tr_d2=tr_d2, k_sg=k_sg)[1, 0]
    assert theta > 0
    e, rho, d = E, RHO_S, D
    g0 = 1.0 / (1.0 - (eps_s / EPS_MAX) ** (1.0 / 3.0))
    sp = math.sqrt(math.pi)
    k1 = 2 * (1 + e) * rho * g0
    k3 = d * rho / 2 * (sp / (3 * (3 - e)) * (0.5 * (3 * e + 1) + 0.4 * (1 + e) * (3 * e - 1) * eps_s * g0)
                        + 8 * eps_s * g0 * (1 + e) / (5 * sp))
    k2 = 4 * d * rho * (1 + e) * eps_s * g0 / (3 * sp) - 2.0 / 3.0 * k3
    k4 = 12 * (1 - e * e) * rho * g0 / (d * sp)
    s = math.sqrt(theta)
    production = -k1 * eps_s**2 * theta * tr_d + k2 * eps_s * s * tr_d**2 + 2 * k3 * eps_s * s * tr_d2
    sinks = k4 * eps_s**2 * theta**1.5 + 3 * k_sg * theta
    # float32 kernel: residual relative to the sinks at the float32 level
    assert abs(production - sinks) <= 1e-4 * sinks


def _cells(eps_row, u_row, drag_coeff_row=None, h=1e-3, eps_s_min=1e-8):
    """ktgf_cells on a (n, 1, 1) row of cells; returns (theta, p_s) as float64 rows."""
    n = len(eps_row)
    params = ktgf.make_ktgf_params(particle_diameter=D, particle_density=RHO_S, restitution=E, packing=EPS_MAX,
                                   eps_s_min=eps_s_min)
    out = {k: wp.zeros((n, 1, 1), dtype=float) for k in ("g0", "theta", "p_s", "mu_s", "mu_fric")}
    drag = None
    if drag_coeff_row is not None:
        drag = wp.array(np.asarray(drag_coeff_row, np.float64).reshape(n, 1, 1), dtype=wp.float64)
    ktgf.ktgf_cells(params, h, wp.array(np.asarray(eps_row, np.float32).reshape(n, 1, 1), dtype=float),
                    wp.array(np.asarray(u_row, np.float32).reshape(n, 1, 1, 3), dtype=wp.vec3),
                    cell_g0=out["g0"], cell_theta=out["theta"], cell_p_s=out["p_s"], cell_mu_s=out["mu_s"],
                    cell_mu_fric=out["mu_fric"], cell_drag_coeff=drag)
    return out["theta"].numpy().ravel().astype(np.float64), out["p_s"].numpy().ravel().astype(np.float64)


def test_isolated_moving_parcel_has_no_solids_strain():
    # One parcel moving at (5, 0.87, 0) m/s, spread by the cloud-in-cell weights over cells 2 and 3 of a
    # row of 6 (eps_s 0.010 and 0.006); the other cells are empty (deposited velocity 0 there). The solids
    # velocity gradient exists only between cells holding solids: one-sided 2 -> 3 and 3 -> 2, both 0, so
    # D = 0, Theta = 0, p_s = 0. (Central differences against the empty cells gave a false strain
    # |v|/(2h) = 2500 1/s in both cells.)
    eps = [0.0, 0.0, 0.010, 0.006, 0.0, 0.0]
    v = [5.0, 0.87, 0.0]
    u = [[0, 0, 0], [0, 0, 0], v, v, [0, 0, 0], [0, 0, 0]]
    theta, p_s = _cells(eps, u)
    assert np.all(theta == 0.0) and np.all(p_s == 0.0)
    # a single occupied cell: no neighbour with solids on any axis, no strain either
    theta, p_s = _cells([0.0, 0.016, 0.0], [[0, 0, 0], v, [0, 0, 0]])
    assert np.all(theta == 0.0) and np.all(p_s == 0.0)


def _shear_row(last: float, h: float = 1e-3, gamma: float = 10.0):
    """A row of 5 cells with solids in cells 1..3 (eps_s 0.3, 0.3, ``last``) in simple shear u_y = gamma x:
    (h, eps_s row, solids velocity row)."""
    x = (np.arange(5) + 0.5) * h
    eps = [0.0, 0.3, 0.3, last, 0.0]
    u = [[0.0, gamma * xi if 1 <= n <= 3 else 0.0, 0.0] for n, xi in enumerate(x)]
    return h, eps, u


def test_solids_strain_is_one_sided_next_to_empty_cells():
    # Solids in cells 1..3 of a row of 5 with u_y = gamma x (simple shear D_xy = gamma/2, tr D = 0,
    # D:D = gamma^2/2 = 50 for gamma = 10 1/s): cell 2 central, cells 1 and 3 one-sided against the
    # centre, both exact for a linear profile, so all three take the simple-shear hand value of
    # test_algebraic_theta_simple_shear_hand_value at eps_s = 0.3: Theta = 9.48304e-6.
    h, eps, u = _shear_row(last=0.3)
    theta, _ = _cells(eps, u, h=h)
    assert theta[1:4] == pytest.approx([9.48304e-6] * 3, rel=1e-4)
    assert theta[0] == 0.0 and theta[4] == 0.0
    # the deposit's sum beta V per cell enters as K_sg = sum beta V / h^3: 3e-6 kg/s in 1e-9 m^3 = 3000
    # kg/(m^3 s), the hand value of test_algebraic_theta_with_gas_exchange_hand_value: Theta = 1.963953e-6
    theta, _ = _cells(eps, u, drag_coeff_row=[0.0, 3e-6, 3e-6, 3e-6, 0.0], h=h)
    assert theta[1:4] == pytest.approx([1.963953e-6] * 3, rel=1e-4)


def test_the_dilute_limit_leaves_cells_of_less_than_a_particle_without_a_solids_phase():
    # The simple shear of the test above (u_y = gamma x, eps_s = 0.3) with a fringe cell of eps_s 0.05 at its end.
    # Without a dilute limit the fringe cell holds a solids phase: its Theta is the algebraic root at eps_s 0.05,
    # which exceeds the dense cells' (Theta ~ 1 / eps_s in the dilute limit). With the limit 0.065 (one 1.2 mm
    # particle in a 2.4 mm cell) it holds none (Theta = p_s = 0), and its neighbour's strain is taken one-sided
    # against the dense cell, exact for the linear profile: the simple-shear hand value 9.48304e-6 m^2/s^2.
    h, eps, u = _shear_row(last=0.05)
    theta, p_s = _cells(eps, u, h=h)
    assert theta[3] > theta[2] > 0.0 and p_s[3] > 0.0
    theta, p_s = _cells(eps, u, h=h, eps_s_min=math.pi / 6 * 1.2**3 / 2.4**3)
    assert theta[3] == 0.0 and p_s[3] == 0.0
    assert theta[1:3] == pytest.approx([9.48304e-6] * 2, rel=1e-4)


def test_ktgf_refuses_a_dilute_limit_outside_zero_to_packing():
    from hel_warp.errors import ConfigError
    from hel_warp.hel import KtgfCollision

    for bad in (0.0, 0.63, 0.7):
        with pytest.raises(ConfigError, match="dilute_limit"):
            KtgfCollision(particle_diameter=D, particle_density=RHO_S, dilute_limit=bad)


def test_radial_distribution_diverges_at_packing():
    eps = EPS_MAX * (1.0 - np.array([1e-1, 1e-2, 1e-3, 1e-4]))
    g0 = closures(eps)[0]
    assert np.all(np.diff(g0) > 0)
    # 1/(1 - (1-x)^(1/3)) ~ 3/x for small x: 3e4 at x = 1e-4
    assert g0[-1] == pytest.approx(3.0 / 1e-4, rel=0.02)
    assert closures(1e-9)[0, 0] == pytest.approx(1.0, abs=2e-3)  # dilute: g0 -> 1 (1/(1 - 1.6e-3))


def test_kinetic_pressure_limit():
    # eps_s -> 0: p_s -> eps_s rho_s Theta (collisional part ~ eps_s^2)
    for eps in (1e-4, 1e-6):
        p_s = closures(eps, theta=0.5)[2, 0]
        assert p_s / (eps * RHO_S * 0.5) == pytest.approx(1.0, rel=2 * (1 + E) * eps * 1.1 + 1e-6)


def test_schaeffer_zero_below_friction_packing_and_hand_value_above():
    # I_2D = 25 (simple shear D_xy = 5), phi = 30 deg, Theta = 0.01
    rows = closures([0.5, 0.61, 0.62], theta=0.01, i2d=25.0)
    assert rows[5, 0] == 0.0 and rows[5, 1] == 0.0
    # eps 0.62: g0 = 1/(1 - (0.62/0.63)^(1/3)) = 187.9964; p_s = 0.62*1000*0.01*(1 + 2*1.9*0.62*187.9964)
    #   = 2752.302 Pa; mu_fr = p_s sin30/(2*5) = 137.615 Pa s
    assert rows[2, 2] == pytest.approx(2752.302, rel=2e-4)   # float32 near packing: g0 loses digits
    assert rows[5, 2] == pytest.approx(137.615, rel=2e-4)


def test_collision_acceleration_is_minus_grad_ps_over_eps_rho():
    from kernels.interp import make_cell_grid

    shape = (4, 4, 4)
    grad = np.zeros(shape + (3,), np.float32)
    grad[...] = (120.0, -30.0, 7.5)  # Pa/m, uniform
    eps = np.full(shape, 0.2, np.float32)
    x = wp.array(np.array([[1.3e-3, 2.1e-3, 0.7e-3], [3.9e-3, 0.2e-3, 2.5e-3]], np.float32), dtype=wp.vec3)
    rho = wp.array(np.array([1000.0, 2500.0], np.float32), dtype=float)
    out = wp.zeros(2, dtype=wp.vec3)
    ktgf.collision_acceleration(make_cell_grid((0, 0, 0), 1e-3, shape), 1e-8, x, rho,
                                wp.array(grad, dtype=wp.vec3), wp.array(eps, dtype=float), out)
    expect = -np.array([120.0, -30.0, 7.5])[None, :] / (0.2 * np.array([1000.0, 2500.0])[:, None])
    assert np.allclose(out.numpy(), expect, rtol=1e-6)


def test_cell_pressure_gradient_of_linear_field_is_exact():
    shape = (5, 4, 3)
    h = 0.01
    i, j, k = np.meshgrid(*[np.arange(n) for n in shape], indexing="ij")
    field = (2.0 * i - 3.0 * j + 0.5 * k).astype(np.float32) * h  # gradient (2, -3, 0.5)
    out = wp.zeros(shape, dtype=wp.vec3)
    ktgf.cell_gradient(h, wp.array(field, dtype=float), out)
    assert np.allclose(out.numpy(), [2.0, -3.0, 0.5], rtol=1e-5)
