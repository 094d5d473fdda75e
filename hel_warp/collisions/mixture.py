"""Binary (and wider) size mixtures of spheres: species, fractions, pair types and the kinetic theory of their
collisions (host-side numpy; used by the data set's metrics, the cases and the report).

Fractions. Species i (mean diameter mu_i, standard deviation sigma_i of normal sizes, one density) has a mean
particle mass proportional to E[d_i^3] = mu_i^3 + 3 mu_i sigma_i^2, so mass fractions w_i and number fractions
x_i convert as x_i = (w_i / E[d_i^3]) / sum_k (w_k / E[d_k^3]). The Sauter mean diameter of the mixture is
d_32 = sum x_i E[d_i^3] / sum x_i E[d_i^2] (the one diameter the single-size KTGF closures get).

Kinetic theory of a homogeneous mixture of smooth inelastic hard spheres whose species have Maxwellian
velocities at granular temperatures Theta_i = <|c_i|^2>/3 (m^2/s^2; T_i = m_i Theta_i is the temperature in
energy units, equipartition means T_1 = T_2), restitution e (Chapman & Cowling 1970; Jenkins & Mancini 1987;
Garzo & Dufty 1999, Phys. Rev. E 60: 5706, their Maxwellian (zeroth-order) cooling rates):

- relative velocity of an (i, j) pair: Maxwellian, variance per component s_ij^2 = Theta_i + Theta_j;
- collision rate per unit volume (each pair once: half of it for i = j)
  R_ij = n_i n_j g0_ij pi sigma_ij^2 <|g|>,  <|g|> = sqrt(8/pi) s_ij,  sigma_ij = (d_i + d_j)/2;
- energy gained by species i in collisions with j, per unit volume (the same formula for j = i counts both
  partners of each i-i collision), mu_red = m_i m_j / (m_i + m_j), mu_ji = m_j / (m_i + m_j),
  lambda_ij = (T_i - T_j) / ((m_i + m_j) s_ij^2) (the correlation of the centre-of-mass velocity with g):
  W_ij = 4 sqrt(2 pi) n_i n_j g0_ij sigma_ij^2 mu_red (1 + e) s_ij^3 [-lambda_ij - mu_ji (1 - e) / 2],
  so dTheta_i/dt = (2/3) sum_j W_ij / (n_i m_i). One species: dTheta/dt = -8 (1 - e^2) g0 eps Theta^(3/2) /
  (sqrt(pi) d), Haff's law; e = 1: W_ij + W_ji = 0 (energy exchanged, not lost);
- g0_ij: the Boublik-Mansoori-Carnahan-Starling-Leland contact value (Boublik 1970; Mansoori et al. 1971),
  xi_k = (pi/6) sum n_i d_i^k, g0_ij = 1/(1 - xi_3) + 3 D xi_2/(1 - xi_3)^2 + 2 D^2 xi_2^2/(1 - xi_3)^3,
  D = d_i d_j / (d_i + d_j); one species: Carnahan-Starling (1 - eps/2)/(1 - eps)^3.
The inelastic mixture does not keep equipartition: in the homogeneous cooling state T_i / T_j tends to a
constant != 1 (Garzo & Dufty 1999); ``cool_mixture`` integrates the Maxwellian rates above to it.
"""

from __future__ import annotations

import math

import numpy as np


def second_size(d2, f2, diameter: float, fraction_option: str, example: str):
    """The second species of a two-size case from its options (``--diameter2`` and the fraction option
    ``fraction_option``, e.g. ``--mass-fraction2``): None when neither is given, else (d2, f2) checked with one-line
    errors (both given, d2 > 0, 0 < f2 < 1, d2 differs from ``diameter``). ``example``: the fraction shown in
    the error that asks for both."""
    from hel_warp.errors import ConfigError

    if d2 is None and f2 is None:
        return None
    if d2 is None or f2 is None:
        raise ConfigError(f"a mixture needs both --diameter2 and {fraction_option} (e.g. --diameter2 475e-6 "
                          f"{fraction_option} {example})")
    if not d2 > 0.0:
        raise ConfigError(f"--diameter2 must be > 0 m (got {d2:g}); e.g. 475e-6")
    if not 0.0 < f2 < 1.0:
        raise ConfigError(f"{fraction_option} must lie in (0, 1) (got {f2:g}); 0 or 1 is one size: drop --diameter2")
    if abs(d2 - diameter) < 1e-3 * diameter:
        raise ConfigError(f"--diameter2 {d2:g} m equals --diameter; a mixture needs two sizes")
    return float(d2), float(f2)


def species_weights(value, species: int, option: str = "--particles-per-parcel") -> tuple[int, ...]:
    """Real particles per parcel of each species from ``option``: one value W (every species) or, with a second
    size, two comma-separated values ``W1,W2`` (species 1 = --diameter, species 2 = --diameter2). ``value``: the
    option's text, a number, or a sequence of numbers. Integers >= 1 only (a parcel holds whole particles); a
    ConfigError (one line, what to change) otherwise. Returns one int per species (``species`` of them)."""
    from hel_warp.errors import ConfigError

    if isinstance(value, str):
        items = [s.strip() for s in value.split(",")]
    elif isinstance(value, (list, tuple)):
        items = list(value)
    else:
        items = [value]
    if len(items) > 2:
        raise ConfigError(f"{option} {value}: give one value W (every species) or two values W1,W2")
    if len(items) == 2 and species < 2:
        raise ConfigError(f"{option} {value}: two values W1,W2 (one per species) need a second size "
                          "(--diameter2); give one value W")
    weights = []
    for item in items:
        try:
            number = float(item)
        except (TypeError, ValueError):
            number = float("nan")
        if not (math.isfinite(number) and number >= 1.0 and number == int(number)):
            raise ConfigError(f"{option} {value}: every weight must be an integer >= 1 (real particles per parcel; "
                              "e.g. 8 or 1,8)")
        weights.append(int(number))
    if len(weights) == 1:
        weights = weights * species
    return tuple(weights)


def mean_cube(means, stds) -> np.ndarray:
    """E[d^3] = mu^3 + 3 mu sigma^2 of normal sizes, m^3 (per species)."""
    mu, sd = np.asarray(means, float), np.asarray(stds, float)
    return mu**3 + 3.0 * mu * sd**2


def number_fractions(mass_fractions, means, stds) -> np.ndarray:
    """Number fraction of each species from its mass fraction (one density): x_i ∝ w_i / E[d_i^3]."""
    per = np.asarray(mass_fractions, float) / mean_cube(means, stds)
    return per / per.sum()


def mass_fractions(number_fractions_, means, stds) -> np.ndarray:
    """Mass fraction of each species from its number fraction (one density): w_i ∝ x_i E[d_i^3]."""
    per = np.asarray(number_fractions_, float) * mean_cube(means, stds)
    return per / per.sum()


def sauter_mean(number_fractions_, means, stds) -> float:
    """Sauter mean diameter d_32 = sum x_i E[d_i^3] / sum x_i E[d_i^2], m."""
    x = np.asarray(number_fractions_, float)
    mu, sd = np.asarray(means, float), np.asarray(stds, float)
    return float((x * mean_cube(mu, sd)).sum() / (x * (mu**2 + sd**2)).sum())


def species_of(diameter, means, stds=None) -> np.ndarray:
    """Species index of each diameter: the nearest mean in units of its standard deviation (plain distance
    where the stds are 0 or not given). (n,) int64."""
    d = np.asarray(diameter, float)[..., None]
    mu = np.asarray(means, float)
    if stds is None or not np.all(np.asarray(stds, float) > 0):
        return np.argmin(np.abs(d - mu), axis=-1)
    return np.argmin(np.abs(d - mu) / np.asarray(stds, float), axis=-1)


def pair_type_names(k: int) -> list[tuple[int, int, str]]:
    """(i, j, name) of the unordered species pairs i <= j: small-small, small-large, large-large for two
    species (species 0 the smaller), ``s0-s1`` style names for more."""
    if k == 2:
        return [(0, 0, "small-small"), (0, 1, "small-large"), (1, 1, "large-large")]
    return [(i, j, f"s{i}-s{j}") for i in range(k) for j in range(i, k)]


def pair_type_of(species1, species2) -> np.ndarray:
    """(n, 2) unordered species pair (min, max) of each row."""
    a, b = np.asarray(species1), np.asarray(species2)
    return np.stack([np.minimum(a, b), np.maximum(a, b)], axis=-1)


# ------------------------------------------------------------------------------------------- kinetic theory
def contact_g0(number_densities, diameters) -> np.ndarray:
    """(K, K) radial distribution at contact g0_ij of a hard-sphere mixture (BMCSL, module docstring)."""
    n, d = np.asarray(number_densities, float), np.asarray(diameters, float)
    xi2 = math.pi / 6.0 * float((n * d**2).sum())
    xi3 = math.pi / 6.0 * float((n * d**3).sum())
    dd = d[:, None] * d[None, :] / (d[:, None] + d[None, :])
    return 1.0 / (1.0 - xi3) + 3.0 * dd * xi2 / (1.0 - xi3) ** 2 + 2.0 * dd**2 * xi2**2 / (1.0 - xi3) ** 3


def collision_rates(number_densities, diameters, masses, theta, g0=None) -> np.ndarray:
    """(K, K) collisions per unit volume and second of each unordered pair type (upper triangle; i = j the
    collisions inside species i), Maxwellian species at ``theta`` (m^2/s^2)."""
    n, d, th = (np.asarray(v, float) for v in (number_densities, diameters, theta))
    g0 = contact_g0(n, d) if g0 is None else np.asarray(g0, float)
    sig = 0.5 * (d[:, None] + d[None, :])
    s = np.sqrt(th[:, None] + th[None, :])
    rate = n[:, None] * n[None, :] * g0 * math.pi * sig**2 * math.sqrt(8.0 / math.pi) * s
    rate[np.diag_indices_from(rate)] *= 0.5
    return np.triu(rate)


def temperature_rates(number_densities, diameters, masses, theta, restitution: float, g0=None) -> np.ndarray:
    """dTheta_i/dt of each species from collisions (Maxwellian rates, module docstring), m^2/s^3."""
    n, d, m, th = (np.asarray(v, float) for v in (number_densities, diameters, masses, theta))
    e = float(restitution)
    g0 = contact_g0(n, d) if g0 is None else np.asarray(g0, float)
    sig = 0.5 * (d[:, None] + d[None, :])
    s2 = th[:, None] + th[None, :]
    msum = m[:, None] + m[None, :]
    mu_red = m[:, None] * m[None, :] / msum
    mu_ji = m[None, :] / msum
    temp = m * th
    lam = (temp[:, None] - temp[None, :]) / (msum * s2)
    w = (4.0 * math.sqrt(2.0 * math.pi) * n[:, None] * n[None, :] * g0 * sig**2 * mu_red * (1.0 + e) * s2**1.5
         * (-lam - mu_ji * (1.0 - e) / 2.0))
    return (2.0 / 3.0) * w.sum(axis=1) / (n * m)


def cool_mixture(number_densities, diameters, masses, theta0, restitution: float, times, substeps: int = 20):
    """Theta_i(t) of the Maxwellian rate equations at ``times`` (s, increasing from 0), RK4 with ``substeps``
    per interval; (len(times), K)."""
    n, d, m = (np.asarray(v, float) for v in (number_densities, diameters, masses))
    g0 = contact_g0(n, d)
    t = np.asarray(times, float)
    out = np.zeros((t.size, n.size))
    y = np.asarray(theta0, float).copy()
    out[0] = y
    f = lambda th: temperature_rates(n, d, m, np.maximum(th, 0.0), restitution, g0)  # noqa: E731
    for k in range(1, t.size):
        h = (t[k] - t[k - 1]) / substeps
        for _ in range(substeps):
            k1 = f(y)
            k2 = f(y + 0.5 * h * k1)
            k3 = f(y + 0.5 * h * k2)
            k4 = f(y + h * k3)
            y = y + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        out[k] = y
    return out


def mixture_theta(theta, number_densities, masses) -> np.ndarray:
    """The mixture's granular temperature, mass-weighted: sum n_i m_i Theta_i / sum n_i m_i (kinetic energy of
    the fluctuations over (3/2) rho eps); ``theta`` (..., K)."""
    rho = np.asarray(number_densities, float) * np.asarray(masses, float)
    return (np.asarray(theta, float) * rho).sum(axis=-1) / rho.sum()


# ------------------------------------------------------------------------------------------- models
def model_domain_problem(meta: dict, diameters) -> str | None:
    """Why a surrogate's training domain (``metadata.json`` ``domain``: the d1 / d2 / size_ratio ranges of its
    train rows) does not hold a mixture of ``diameters`` (every size with 2 % slack on the range, and every size
    ratio d_j / d_i), or None when it does."""
    domain = meta.get("domain") or {} if isinstance(meta, dict) else {}
    feats = list(domain.get("features") or [])
    if "d1" not in feats or not ("size_ratio" in feats or "d2" in feats):
        return "it records no training domain of sizes (metadata domain d1 with size_ratio or d2)"
    lo, hi = domain["lo"], domain["hi"]
    for name in ("d1", "d2"):
        if name in feats:
            k = feats.index(name)
            for d in diameters:
                if not 0.98 * lo[k] <= d <= 1.02 * hi[k]:
                    return (f"it was trained for {name} in {lo[k] * 1e6:.0f}-{hi[k] * 1e6:.0f} um, the run has "
                            f"{d * 1e6:.0f} um")
    if "size_ratio" in feats:
        r = feats.index("size_ratio")
        for a in diameters:
            for b in diameters:
                if not 0.98 * lo[r] <= b / a <= 1.02 * hi[r]:
                    return (f"it was trained for size ratios {lo[r]:.3g}-{hi[r]:.3g}, the run needs {b / a:.3g}")
    return None
