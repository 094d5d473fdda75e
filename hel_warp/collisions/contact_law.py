"""Host side of the contact law: damping from a restitution coefficient, linear stiffness.

The normal dashpot of ``kernels/hertz.py`` is ``eta = c sqrt(m* k) delta^{(p-1)/2}`` with
``p = 3/2`` (Hertz, ``k = k_H = 4/3 E* sqrt(R*)``; the Tsuji, Tanaka & Ishida 1992 form) or
``p = 1`` (linear spring–dashpot, Cundall & Strack 1979; ``c = 2 zeta``). With the scaling
``delta = delta0 x``, ``t = T tau``, ``T^2 = m*/(k delta0^{p-1})``, ``delta0 = v T`` the normal
equation of motion of an impact at approach speed ``v`` becomes the dimensionless oscillator::

    x'' = -max(0, x^p + c x^{(p-1)/2} x'),   x(0) = 0, x'(0) = 1,

whose restitution ``e = -x'(end)`` depends on ``c`` alone — not on speed, size, mass or modulus.
The total force is clipped at zero (no attraction), so the classical closed forms, which
assume the force may turn attractive, return a higher ``e`` (docs/physics/references.md, "damping pitfall";
Thornton, Cummins & Cleary 2013, Powder Technol. 233: 30-46). ``damping_coefficient`` therefore
inverts ``e(c)`` of the clipped oscillator by root bracketing (Brent), once per distinct
``(e, model)``, cached (many distinct values at once: a table of e(c), interpolated). The raw
forms stay selectable:

- ``form="tsuji"``: ``c = sqrt(2) alpha(e)``, the polynomial of Tsuji et al. (1992) as in LAMMPS
  ``tsuji`` damping with the effective-mass factor sqrt(2) (Hertz model only);
- ``form="liggghts"``: LIGGGHTS ``hertz/material``, ``gamma_n = 2 sqrt(5/6) |beta| sqrt(S_n m*)``,
  ``S_n = 2 E* sqrt(R* delta)`` = 3/2 k_H delta^{1/2}, i.e. ``c = sqrt(5) |beta|``,
  ``beta = ln e / sqrt(ln^2 e + pi^2)``; for the linear model the textbook
  ``c = 2 zeta = -2 ln e / sqrt(ln^2 e + pi^2)``.
Both give a higher e than asked when the force is clipped (measured in tests/test_hertz.py).

Linear stiffness default (``linear_stiffness_matching_hertz``): the elastic linear contact lasts
``pi sqrt(m*/k_n)``; the Hertz contact lasts ``t_c = 2.868 (m*^2/(R* E*^2 v))^{1/5}`` (Johnson
1985 §11.4). ``k_n = m* (pi / t_c(v_ref))^2`` makes both equal at the reference speed ``v_ref``
(default ``REFERENCE_SPEED`` = 1 m/s); the linear contact is then longer than the Hertz one above
``v_ref`` and shorter below it.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from hel_warp.errors import ConfigError

MODELS = ("hertz", "linear")
"""Normal contact models; the index is ``ContactParams.model``."""
DAMPING_FORMS = ("calibrated", "tsuji", "liggghts")
"""How the dimensionless damping c is obtained from e (see the module docstring)."""
REFERENCE_SPEED = 1.0
"""m/s: approach speed at which the default linear stiffness matches the Hertz contact duration."""
HERTZ_DURATION_FACTOR = 2.868
"""t_c = 2.868 (m*^2/(R* E*^2 v))^{1/5}, Johnson (1985) §11.4 (= 2.943 delta_max / v)."""
_MODEL_EXPONENT = {"hertz": 1.5, "linear": 1.0}
_C_MAX = 1.0e3
TABLE_THRESHOLD = 16
"""Above this many distinct restitution values in one call, c(e) comes from a table of e(c)
(161 integrations, ~3 s once per process and model) with monotone cubic (PCHIP) interpolation,
|e(c_table) - e| < 1e-5 (tests/test_hertz.py); below it, each value is solved by Brent's method."""


def _check_model(model: str) -> None:
    if model not in MODELS:
        raise ConfigError(f"contact model must be one of {', '.join(MODELS)} (got {model!r})")


def clipped_oscillator_restitution(c: float, model: str = "hertz") -> float:
    """Restitution of the dimensionless clipped damped oscillator for damping ``c >= 0``.

    Integrates ``x'' = -max(0, x^p + c x^{(p-1)/2} x')`` from ``x = 0, x' = 1`` until the force
    vanishes while separating (after that the bodies coast apart at constant speed) with an
    adaptive 8th-order Runge–Kutta (scipy DOP853, rtol 1e-11).
    """
    from scipy.integrate import solve_ivp

    _check_model(model)
    if not c >= 0.0:
        raise ConfigError(f"damping coefficient must be >= 0 (got {c})")
    p = _MODEL_EXPONENT[model]
    q = 0.5 * (p - 1.0)

    def force(x, xd):
        xp = max(x, 0.0)
        return xp**p + c * xp**q * xd

    def rhs(_t, y):
        return [y[1], -max(force(y[0], y[1]), 0.0)]

    def released(_t, y):  # force reaches zero while the bodies separate (or overlap closes)
        return force(y[0], y[1]) if y[1] < 0.0 else 1.0

    released.terminal = True
    released.direction = -1.0
    # the elastic half period is < 4 in these units for both models; damping only shortens it
    sol = solve_ivp(rhs, (0.0, 50.0), [0.0, 1.0], method="DOP853", rtol=1e-11, atol=1e-13,
                    events=released, max_step=0.05)
    if sol.status != 1 or not len(sol.t_events[0]):
        raise RuntimeError(f"clipped oscillator did not release within tau = 50 for c = {c}")
    return float(-sol.y_events[0][0][1])


@lru_cache(maxsize=4096)
def _calibrated(e: float, model: str) -> float:
    from scipy.optimize import brentq

    if e >= 1.0:
        return 0.0
    e_min = clipped_oscillator_restitution(_C_MAX, model)
    if e <= e_min:
        raise ConfigError(f"restitution {e} is below {e_min:.3g}, the lowest the clipped {model} "
                          "contact reaches; give a larger restitution")
    return float(brentq(lambda c: clipped_oscillator_restitution(c, model) - e, 0.0, _C_MAX,
                        xtol=1e-12, rtol=1e-12))


@lru_cache(maxsize=4)
def _calibration_table(model: str):
    """PCHIP interpolant e -> c built from e(c) on c = 0 and 160 values geometric in [1e-3, 1e3]."""
    from scipy.interpolate import PchipInterpolator

    c = np.concatenate([[0.0], np.geomspace(1e-3, _C_MAX, 160)])
    e = np.array([clipped_oscillator_restitution(float(x), model) for x in c])
    return float(e[-1]), PchipInterpolator(e[::-1], c[::-1])


def tsuji_alpha(e: float) -> float:
    """Tsuji, Tanaka & Ishida (1992) polynomial fit alpha(e) of their damping coefficient."""
    return (1.2728 - 4.2783 * e + 11.087 * e**2 - 22.348 * e**3 + 27.467 * e**4
            - 18.022 * e**5 + 4.8218 * e**6)


def damping_coefficient(e, model: str = "hertz", form: str = "calibrated"):
    """Dimensionless normal damping c for restitution ``e`` (scalar or array; returns the same shape).

    ``form="calibrated"`` (default) returns exactly ``e`` with the clipped force (module docstring).
    """
    _check_model(model)
    if form not in DAMPING_FORMS:
        raise ConfigError(f"damping form must be one of {', '.join(DAMPING_FORMS)} (got {form!r})")
    arr = np.asarray(e, dtype=np.float64)
    if not np.all(np.isfinite(arr)) or np.any(arr <= 0.0) or np.any(arr > 1.0):
        raise ConfigError(f"restitution must lie in (0, 1] (got {e!r})")
    uniq, inverse = np.unique(arr, return_inverse=True)
    out = np.empty_like(uniq)
    if form == "calibrated" and len(uniq) > TABLE_THRESHOLD:
        e_min, table = _calibration_table(model)
        if uniq[0] <= e_min:
            raise ConfigError(f"restitution {uniq[0]} is below {e_min:.3g}, the lowest the clipped {model} "
                              "contact reaches; give a larger restitution")
        out = np.where(uniq >= 1.0, 0.0, table(uniq))
        uniq = uniq[:0]  # done
    for k, value in enumerate(uniq):
        value = float(value)
        if form == "calibrated":
            out[k] = _calibrated(value, model)
        elif form == "tsuji":
            if model != "hertz":
                raise ConfigError("the tsuji damping form applies to the hertz model only; use calibrated")
            out[k] = math.sqrt(2.0) * tsuji_alpha(value)
        else:
            beta = abs(math.log(value)) / math.sqrt(math.log(value) ** 2 + math.pi**2)
            out[k] = math.sqrt(5.0) * beta if model == "hertz" else 2.0 * beta
    result = out[inverse].reshape(arr.shape)
    return float(result) if result.ndim == 0 else result


def hertz_contact_duration(youngs_eff, radius_eff, mass_eff, speed):
    """Elastic Hertz contact duration t_c = 2.868 (m*^2/(R* E*^2 v))^{1/5}, s (Johnson 1985 §11.4)."""
    return HERTZ_DURATION_FACTOR * (np.asarray(mass_eff) ** 2
                                    / (np.asarray(radius_eff) * np.asarray(youngs_eff) ** 2
                                       * np.asarray(speed))) ** 0.2


def linear_stiffness_matching_hertz(youngs_eff, radius_eff, mass_eff, reference_speed=REFERENCE_SPEED):
    """k_n (N/m) whose elastic contact duration pi sqrt(m*/k_n) equals Hertz's t_c at ``reference_speed``."""
    t_c = hertz_contact_duration(youngs_eff, radius_eff, mass_eff, reference_speed)
    return np.asarray(mass_eff) * (math.pi / t_c) ** 2
