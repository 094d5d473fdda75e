"""Binary-collision configurations for the surrogate data set, paper section 4.1.

Velocities follow eq. (16): a speed ``V_mag`` in ``[speed_min, speed_max]`` (paper: 0-20 m/s)
and a direction from ``phi`` (angle from OX) and ``theta`` (angle from OZ),

    u = V sin(theta) cos(phi),  v = V sin(theta) sin(phi),  w = V cos(theta).

Directions are isotropic: ``phi ~ U[0, 2 pi)``, ``cos(theta) ~ U[-1, 1]`` (a uniform ``theta``
would crowd the poles). Three families, Fig. 5 of the paper:

- 0 ``converging``: independent directions; both centres move towards one common point, which
  is put at the origin (the paper: "both particles collide in the centre of the coordinate
  system"). Central impacts reach it at the same instant; oblique ones in turn.
- 1 ``parallel``: one direction, the rear particle faster (which of the two is the rear one is
  drawn at random, so the set is symmetric in the particle labels).
- 2 ``head-on``: opposite directions.

Beyond the paper (the engine meets every impact: any angle, |g| from ~0.01 to 20+ m/s):

- impact offset ``b / (r1 + r2)`` in ``[0, max_offset]`` (default ``sin 89.8 deg``), three kinds of
  rows drawn per row: a fraction ``central_fraction`` is central (offset 0, as in the paper); a
  fraction ``grazing_fraction`` has its incidence angle ``chi`` (between ``g`` and the normal,
  ``offset = sin chi``) uniform in ``[grazing_angle, asin(max_offset)]`` (grazing oversampled:
  random collisions put only 3 % of their impacts beyond 80 deg); the others have
  ``offset = max_offset * sqrt(U)``, uniform in ``b^2``: impact points uniform over the collision
  disc, as real collisions in a granular gas (docs/physics/references.md "Collisions in a granular gas"). The contact
  normal at first touch is ``n = sqrt(1 - b^2) g_hat + b p_hat`` (from 1 to 2), ``g = v1 - v2``,
  ``p_hat`` perpendicular to ``g`` (in the plane of ``v1, v2`` for the converging family, so
  both straight paths still cross at the common point; any direction otherwise);
- diameters per particle from a normal distribution (paper's size table: 315 +- 8.2 um,
  475 +- 22 um), truncated to ``d > 0``, or from a mixture of species (``mixture_diameters``,
  ``mixture_diameter_stds``): with ``mixture_mass_fractions`` the pair's two species (i, j) are drawn
  in the proportion a mixture meets them (below); without (the deprecated ``--mixture``) each
  particle's species is drawn with equal chance; densities per particle from a normal distribution
  around the material density (standard deviation 0 by default: monodisperse in density; the same
  for every species).

Pair types of a mixture ("the proportion a mixture meets them"). Species i has mass fraction w_i and
mean particle mass proportional to E[d_i^3] = mu_i^3 + 3 mu_i sigma_i^2 (normal sizes), so its number
fraction is x_i = (w_i / E[d_i^3]) / sum_k (w_k / E[d_k^3]). In a homogeneous mixture the collision rate
per unit volume of an (i, j) pair is n_i n_j g0_ij pi sigma_ij^2 <|g|>_ij (Chapman & Cowling; for
i = j half of it, each pair once), sigma_ij = (d_i + d_j)/2. The data set draws every particle's
velocity from one distribution whatever its size (eq. 16), so <|g|> is the same for every pair type and
the rows' pair types follow P(k1 = i, k2 = j) = x_i x_j E[(d_i + d_j)^2] / Z (ordered labels: a cross
pair is (i, j) or (j, i) with equal chance; E[(d_i + d_j)^2] = (mu_i + mu_j)^2 + sigma_i^2 + sigma_j^2).
That is the mixture of the rig, where both sizes ride the same gas streams; it leaves out g0_ij (1 +
O(eps_s): 1.0-1.03 at eps_s <= 0.01) and the equipartition factor sqrt(1/m_i + 1/m_j) of a gas at rest
(the cooling box), which would raise the share of small-small pairs. 315/475 um at mass fractions
0.5/0.5: x = 0.774/0.226, pair types small-small 47 %, small-large 44 %, large-large 9 %.

Every configuration collides, starts apart and touches after ``touch_time``. The pair is built
at first touch (``x2 - x1 = (r1 + r2) n``) and moved back along straight lines by
``touch_time``; then ``|x2 - x1|^2 = (r1+r2)^2 + 2 t (r1+r2) (g.n) + t^2 |g|^2 > (r1+r2)^2``,
and the first touch of ballistic motion is exactly at ``t = touch_time`` with normal ``n``.

- relative speeds down to ``min_relative_speed`` (default 0.01 m/s): a fraction
  ``slow_fraction`` of the rows has both velocities scaled by one factor so that ``|g|`` is
  log-uniform in ``[min_relative_speed, |g|]`` (the family geometry is kept: directions are
  unchanged); speeds uniform in ``[0, 20]`` alone put almost no pair below 0.5 m/s.

Floors on the approach: ``|g| >= min_relative_speed`` and ``g.n = |g| sqrt(1 - b^2) >=
min_normal_speed`` (default 1e-3 m/s: below it the float32 DEM moves the pair by less than ~3 ulps of
its position per step and can miss the contact; the paper's set used 0.05 m/s, which drops most
grazing slow impacts; the engine clamps a slower pair into the domain at its own incidence). Candidates breaking a rule (approach too slow, a converging pair whose
common point lies behind one particle or whose directions are parallel within ~0.06 degrees,
non-positive sizes or densities) are redrawn. The start positions ``x1, x2`` put the common
point (converging) or the first contact point (other families) at the origin; the DEM gets
``contact_frame_positions()`` instead (contact point at the origin, the same physics, no float32
round-off from a far common point).

``paper_spec_options()`` gives the options of the earlier, paper-like set (half central, offsets up
to 0.95, no grazing or slow oversampling, normal speed >= 0.05 m/s): with them the rows are the
same bytes as before the grazing and slow options existed (the extra random draws are only made
when those options are on).

Reproducibility: rows are drawn in blocks of ``BLOCK_ROWS``; block ``j`` uses the generator
``numpy.random.default_rng(SeedSequence(seed, spawn_key=(j,)))``, so row ``k`` depends on
``(seed, k)`` and the spec only, not on how rows are grouped into chunks or workers.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from hel_warp.errors import ConfigError

FAMILIES = ("converging", "parallel", "head-on")
CONVERGING, PARALLEL, HEAD_ON = 0, 1, 2

BLOCK_ROWS = 1024
"""Rows per random-number block (fixed: changing it changes every data set)."""

GRAZING_MAX_OFFSET = math.sin(math.radians(89.8))
"""Default largest impact offset: incidence angles up to 89.8 deg (beyond, the float32 DEM cannot resolve the
contact: its depth R (1 - b) falls below ~1e-9 m)."""

PAPER_LIKE_OPTIONS = {"central_fraction": 0.5, "grazing_fraction": 0.0, "max_offset": 0.95, "slow_fraction": 0.0,
                      "min_normal_speed": 0.05}
"""Options that reproduce the earlier set (half central, offsets <= 0.95, normal speed >= 0.05 m/s)."""


def paper_spec_options() -> dict:
    """``ConfigurationSpec`` / ``make_spec`` keyword options of the earlier, paper-like set."""
    return dict(PAPER_LIKE_OPTIONS)


PAPER_DIAMETER_STD = {315e-6: 8.2e-6, 475e-6: 22e-6}
"""Standard deviation of the diameter (m) for the paper's two sizes (m), from its size table."""


def paper_diameter_std(diameter_mean: float) -> float | None:
    """The paper's standard deviation for ``diameter_mean`` (m), or None for another size."""
    for mean, std in PAPER_DIAMETER_STD.items():
        if math.isclose(diameter_mean, mean, rel_tol=1e-6):
            return std
    return None


@dataclass(frozen=True, kw_only=True)
class ConfigurationSpec:
    """How configurations are drawn (SI units). Validated at construction."""

    diameter_mean: float
    """Mean particle diameter, m."""
    diameter_std: float
    """Standard deviation of the diameter, m (0: monodisperse)."""
    mixture_diameters: tuple[float, ...] = ()
    """A binary (or wider) mixture: each particle's mean diameter drawn with equal chance from these
    (m), its standard deviation from ``mixture_diameter_stds``; empty (default): one size
    ``diameter_mean`` +- ``diameter_std``."""
    mixture_diameter_stds: tuple[float, ...] = ()
    """Standard deviations of ``mixture_diameters``, m (same length)."""
    mixture_mass_fractions: tuple[float, ...] = ()
    """Mass fraction of each species of ``mixture_diameters`` (same length, each > 0, summing to 1): the
    pair types are then drawn in the proportion the mixture meets them (module docstring); empty: each
    particle's species with equal chance (the deprecated ``--mixture`` set, bytes unchanged)."""
    density_mean: float = 1000.0
    """Mean particle density, kg/m^3 (the material density)."""
    density_std: float = 0.0
    """Standard deviation of the particle density, kg/m^3."""
    speed_min: float = 0.0
    """Lowest particle speed V_mag, m/s (paper: 0)."""
    speed_max: float = 20.0
    """Highest particle speed V_mag, m/s (paper: 20)."""
    family_weights: tuple[float, float, float] = (1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0)
    """Probabilities of the converging, parallel and head-on families."""
    central_fraction: float = 0.1
    """Fraction of central impacts (offset 0, as the paper); the rest are oblique."""
    grazing_fraction: float = 0.3
    """Fraction of rows whose incidence angle is uniform in [grazing_angle, asin(max_offset)]."""
    grazing_angle: float = 60.0
    """Smallest incidence angle of the grazing rows, degrees (60: with 70 the 60-70 deg band was the
    thinnest of the set, between the uniform-b^2 share and the grazing one)."""
    max_offset: float = GRAZING_MAX_OFFSET
    """Largest impact offset b / (r1 + r2) of an oblique impact, in [0, 1) (default sin 89.8 deg)."""
    slow_fraction: float = 0.3
    """Fraction of rows whose relative speed is rescaled log-uniform in [min_relative_speed, |g|]."""
    min_relative_speed: float = 0.01
    """Smallest relative speed |v1 - v2| at first touch, m/s (> 0)."""
    min_normal_speed: float = 1e-3
    """Smallest normal approach speed (v1 - v2).n at first touch, m/s (>= 0; the paper-like set: 0.05)."""
    touch_time: float = 1e-7
    """Time from the start positions to first touch, s (a couple of DEM steps at most)."""
    spin_fraction: float = 0.0
    """Fraction of rows whose spheres spin before the impact (0: none, the spinless set, bytes unchanged): each
    sphere's spin axis isotropic, its surface speed r|omega| uniform in [0, spin_ratio |v1 - v2|] (drawn from a
    stream of its own, so the rows' other values are those of the spinless set)."""
    spin_ratio: float = 1.5
    """Largest surface speed r|omega| of a spinning row's spheres, in units of the relative speed |v1 - v2| (a sphere
    rolling on a wall into a partner at rest: 1)."""

    def __post_init__(self) -> None:
        values = asdict(self)
        for name, value in values.items():
            if not np.all(np.isfinite(np.asarray(value, dtype=float))):
                raise ConfigError(f"configuration {name} must be finite (got {value!r})")
        if not self.diameter_mean > 0:
            raise ConfigError(f"diameter mean must be > 0 m (got {self.diameter_mean}); e.g. --diameter 315e-6")
        if len(self.mixture_diameters) != len(self.mixture_diameter_stds) or \
                any(not d > 0 for d in self.mixture_diameters) or any(not sd >= 0 for sd in self.mixture_diameter_stds):
            raise ConfigError("mixture diameters must be > 0 m, each with a standard deviation >= 0 m")
        if self.mixture_mass_fractions:
            w = np.asarray(self.mixture_mass_fractions, dtype=float)
            if len(w) != len(self.mixture_diameters) or np.any(w <= 0) or abs(w.sum() - 1.0) > 1e-6:
                raise ConfigError(f"mixture mass fractions must be one per diameter, each > 0, summing to 1 "
                                  f"(got {list(self.mixture_mass_fractions)})")
        if self.diameter_std < 0 or self.density_std < 0:
            raise ConfigError("diameter and density standard deviations must be >= 0")
        if not self.density_mean > 0:
            raise ConfigError(f"density must be > 0 kg/m^3 (got {self.density_mean})")
        if not 0 <= self.speed_min < self.speed_max:
            raise ConfigError(f"need 0 <= speed_min < speed_max (got {self.speed_min}, {self.speed_max}) m/s")
        weights = np.asarray(self.family_weights, dtype=float)
        if weights.shape != (3,) or np.any(weights < 0) or not weights.sum() > 0:
            raise ConfigError(f"family_weights must be three non-negative numbers, not all 0 (got {self.family_weights})")
        for name in ("central_fraction", "grazing_fraction", "slow_fraction"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"{name} must lie in [0, 1] (got {getattr(self, name)})")
        if self.central_fraction + self.grazing_fraction > 1.0 + 1e-12:
            raise ConfigError(f"central_fraction + grazing_fraction must be <= 1 (got {self.central_fraction} + "
                              f"{self.grazing_fraction}); lower --grazing-fraction or leave it unset")
        if not 0.0 <= self.max_offset < 1.0:
            raise ConfigError(f"max_offset must lie in [0, 1) (got {self.max_offset})")
        if not 0.0 <= self.grazing_angle < 90.0:
            raise ConfigError(f"grazing_angle must lie in [0, 90) degrees (got {self.grazing_angle})")
        if self.grazing_fraction > 0 and math.sin(math.radians(self.grazing_angle)) > self.max_offset:
            raise ConfigError(f"grazing_angle {self.grazing_angle} deg lies beyond max_offset {self.max_offset} "
                              f"(= {math.degrees(math.asin(self.max_offset)):.2f} deg); lower it or raise max_offset")
        if not self.min_normal_speed >= 0:
            raise ConfigError(f"min_normal_speed must be >= 0 m/s (got {self.min_normal_speed})")
        if not self.min_relative_speed > 0:
            raise ConfigError(f"min_relative_speed must be > 0 m/s (got {self.min_relative_speed}); 0.01 is sensible")
        if max(self.min_normal_speed, self.min_relative_speed) >= 2 * self.speed_max:
            raise ConfigError("min_normal_speed and min_relative_speed must be below 2 x speed_max, "
                              "or no pair can collide")
        if not self.touch_time > 0:
            raise ConfigError(f"touch_time must be > 0 s (got {self.touch_time})")
        if not 0.0 <= self.spin_fraction <= 1.0:
            raise ConfigError(f"spin_fraction must lie in [0, 1] (got {self.spin_fraction})")
        if not self.spin_ratio > 0:
            raise ConfigError(f"spin_ratio must be > 0 (got {self.spin_ratio}); 1.5 covers a sphere rolling into another")

    def as_dict(self) -> dict:
        out = asdict(self)
        out["family_weights"] = [float(w) for w in self.family_weights]
        if not self.mixture_diameters:  # the one-size set keeps its earlier attrs
            del out["mixture_diameters"], out["mixture_diameter_stds"]
        else:
            out["mixture_diameters"] = [float(d) for d in self.mixture_diameters]
            out["mixture_diameter_stds"] = [float(d) for d in self.mixture_diameter_stds]
        if not self.spin_fraction:  # the spinless set keeps its earlier attrs
            del out["spin_fraction"], out["spin_ratio"]
        if not self.mixture_mass_fractions:  # the --mixture set keeps its earlier attrs
            del out["mixture_mass_fractions"]
        else:
            out["mixture_mass_fractions"] = [float(w) for w in self.mixture_mass_fractions]
            out["mixture_number_fractions"] = [float(x) for x in self.mixture_number_fractions()]
            out["mixture_pair_probabilities"] = self.mixture_pair_probabilities().tolist()
        return out

    def mixture_number_fractions(self) -> np.ndarray:
        """Number fraction of each species, x_i = (w_i / E[d_i^3]) / sum (module docstring); (K,) float64."""
        mu, sd = np.asarray(self.mixture_diameters, float), np.asarray(self.mixture_diameter_stds, float)
        w = np.asarray(self.mixture_mass_fractions or np.full(mu.size, 1.0 / mu.size), float)
        per_mass = w / (mu**3 + 3.0 * mu * sd**2)
        return per_mass / per_mass.sum()

    def mixture_pair_probabilities(self) -> np.ndarray:
        """(K, K) probabilities of the ordered species pair (k1, k2) of a row: x_i x_j E[(d_i + d_j)^2] / Z
        with mass fractions (the collision proportion, module docstring), else 1/K^2 (equal chance)."""
        k = len(self.mixture_diameters)
        if not self.mixture_mass_fractions:
            return np.full((k, k), 1.0 / k**2)
        mu, sd = np.asarray(self.mixture_diameters, float), np.asarray(self.mixture_diameter_stds, float)
        x = self.mixture_number_fractions()
        cross = (mu[:, None] + mu[None, :]) ** 2 + sd[:, None] ** 2 + sd[None, :] ** 2
        p = x[:, None] * x[None, :] * cross
        return p / p.sum()


@dataclass(frozen=True)
class Configurations:
    """A batch of ``n`` binary-collision configurations (float64, SI units)."""

    config_id: np.ndarray
    """(n,) int64: the row number of each configuration."""
    family: np.ndarray
    """(n,) int8: 0 converging, 1 parallel, 2 head-on."""
    x1: np.ndarray
    """(n, 3) start position of particle 1, m."""
    x2: np.ndarray
    """(n, 3) start position of particle 2, m."""
    v1: np.ndarray
    """(n, 3) velocity of particle 1, m/s."""
    v2: np.ndarray
    """(n, 3) velocity of particle 2, m/s."""
    d1: np.ndarray
    """(n,) diameter of particle 1, m."""
    d2: np.ndarray
    """(n,) diameter of particle 2, m."""
    rho1: np.ndarray
    """(n,) density of particle 1, kg/m^3."""
    rho2: np.ndarray
    """(n,) density of particle 2, kg/m^3."""
    normal: np.ndarray
    """(n, 3) unit contact normal from 1 to 2 at first touch (ballistic motion)."""
    offset: np.ndarray
    """(n,) impact offset b / (r1 + r2), 0 = central."""
    touch_time: float = field(default=0.0)
    """Time from the start positions to first touch, s."""
    omega1: np.ndarray | None = None
    """(n, 3) spin of particle 1 before the impact, rad/s (None: a spinless set)."""
    omega2: np.ndarray | None = None
    """(n, 3) spin of particle 2, rad/s."""

    def __len__(self) -> int:
        return int(self.config_id.shape[0])

    def contact_frame_positions(self) -> tuple[np.ndarray, np.ndarray]:
        """Start positions translated so that the first contact point is the origin, m.

        ``x1 = -r1 n - t v1``, ``x2 = r2 n - t v2`` with ``t = touch_time``: the same motion as
        ``x1, x2`` (a translation), with coordinates of the particle size only.
        """
        r1, r2 = 0.5 * self.d1[:, None], 0.5 * self.d2[:, None]
        return (-r1 * self.normal - self.touch_time * self.v1, r2 * self.normal - self.touch_time * self.v2)

    def inputs(self) -> np.ndarray:
        """(n, 14) float64 rows ``v1 v2 d1 d2 rho1 rho2 n offset`` (the data set's ``inputs``), then for a spinning
        set the spins ``omega1 omega2`` (n, 20)."""
        cols = [self.v1, self.v2, self.d1, self.d2, self.rho1, self.rho2, self.normal, self.offset]
        if self.omega1 is not None:
            cols += [self.omega1, self.omega2]
        return np.column_stack(cols).astype(np.float64)


def _unit(vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    norm = np.linalg.norm(vectors, axis=1)
    safe = np.where(norm > 0, norm, 1.0)
    return vectors / safe[:, None], norm


def _direction(rng: np.random.Generator, n: int) -> np.ndarray:
    """Isotropic unit vectors from the angles of eq. (16)."""
    phi = rng.uniform(0.0, 2.0 * math.pi, n)
    cos_theta = rng.uniform(-1.0, 1.0, n)
    sin_theta = np.sqrt(np.clip(1.0 - cos_theta**2, 0.0, None))
    return np.column_stack([sin_theta * np.cos(phi), sin_theta * np.sin(phi), cos_theta])


def _draw_candidates(spec: ConfigurationSpec, rng: np.random.Generator, family: np.ndarray,
                     central: np.ndarray, grazing: np.ndarray, slow: np.ndarray) -> dict:
    """One candidate per row of ``family`` / ``central`` / ``grazing`` / ``slow``; ``valid`` marks
    those that satisfy every rule. Draws for the grazing and slow options are made only when the
    option is on, so the paper-like spec draws exactly the numbers it always drew."""
    n = family.shape[0]
    if spec.mixture_diameters:
        means, stds = np.asarray(spec.mixture_diameters), np.asarray(spec.mixture_diameter_stds)
        if spec.mixture_mass_fractions:  # pair types in the proportion the mixture meets them
            pair = rng.choice(means.size**2, size=n, p=spec.mixture_pair_probabilities().ravel())
            k1, k2 = pair // means.size, pair % means.size
        else:  # each particle's species with equal chance (the earlier --mixture sets, same bytes)
            k1, k2 = rng.integers(0, means.size, n), rng.integers(0, means.size, n)
        d1 = means[k1] + stds[k1] * rng.standard_normal(n)
        d2 = means[k2] + stds[k2] * rng.standard_normal(n)
    else:
        d1 = rng.normal(spec.diameter_mean, spec.diameter_std, n)
        d2 = rng.normal(spec.diameter_mean, spec.diameter_std, n)
    rho1 = rng.normal(spec.density_mean, spec.density_std, n)
    rho2 = rng.normal(spec.density_mean, spec.density_std, n)
    speed1 = rng.uniform(spec.speed_min, spec.speed_max, n)
    speed2 = rng.uniform(spec.speed_min, spec.speed_max, n)
    dir1 = _direction(rng, n)
    dir2 = _direction(rng, n)
    rear_is_1 = rng.random(n) < 0.5
    offset = np.where(central, 0.0, spec.max_offset * np.sqrt(rng.random(n)))
    random_perp = _direction(rng, n)
    sign = np.where(rng.random(n) < 0.5, -1.0, 1.0)
    if spec.grazing_fraction > 0:
        lo, hi = math.radians(spec.grazing_angle), math.asin(spec.max_offset)
        offset = np.where(grazing, np.sin(lo + (hi - lo) * rng.random(n)), offset)
    if spec.slow_fraction > 0:
        log_fraction = rng.random(n)  # where in [log min_relative_speed, log |g|] the slow row's |g| lands

    converging, parallel, head_on = family == CONVERGING, family == PARALLEL, family == HEAD_ON
    fast_speed, slow_speed = np.maximum(speed1, speed2), np.minimum(speed1, speed2)
    s1 = np.where(parallel, np.where(rear_is_1, fast_speed, slow_speed), speed1)
    s2 = np.where(parallel, np.where(rear_is_1, slow_speed, fast_speed), speed2)
    dir2 = np.where(converging[:, None], dir2, np.where(head_on[:, None], -dir1, dir1))
    v1 = s1[:, None] * dir1
    v2 = s2[:, None] * dir2
    if spec.slow_fraction > 0:
        # one factor for both velocities: |g| log-uniform in [min_relative_speed, |g|], directions kept
        g0 = np.linalg.norm(v1 - v2, axis=1)
        lo_g = math.log(spec.min_relative_speed)
        hi_g = np.log(np.maximum(g0, spec.min_relative_speed))
        scale = np.where(slow & (g0 > 0), np.exp(lo_g + (hi_g - lo_g) * log_fraction) / np.where(g0 > 0, g0, 1.0), 1.0)
        v1 = v1 * scale[:, None]
        v2 = v2 * scale[:, None]

    g_hat, g_norm = _unit(v1 - v2)
    # perpendicular direction of the offset: in the plane of v1, v2 for converging pairs
    in_plane = v1 - np.sum(v1 * g_hat, axis=1)[:, None] * g_hat
    any_perp = random_perp - np.sum(random_perp * g_hat, axis=1)[:, None] * g_hat
    p_hat, p_norm = _unit(np.where(converging[:, None], in_plane, any_perp))
    p_hat *= sign[:, None]
    cos_a = np.sqrt(1.0 - offset**2)
    normal = cos_a[:, None] * g_hat + offset[:, None] * p_hat
    normal /= np.linalg.norm(normal, axis=1)[:, None]

    r1, r2 = 0.5 * d1, 0.5 * d2
    contact = (r1 + r2)[:, None] * normal
    x1c = -r1[:, None] * normal          # contact point at the origin
    x2c = r2[:, None] * normal

    # converging: the common point P = x1c + t1 v1 = x2c + t2 v2 (least squares, 2x2)
    a11 = np.sum(v1 * v1, axis=1)
    a22 = np.sum(v2 * v2, axis=1)
    a12 = -np.sum(v1 * v2, axis=1)
    b1 = np.sum(v1 * contact, axis=1)
    b2 = -np.sum(v2 * contact, axis=1)
    det = a11 * a22 - a12**2
    well_posed = det > 1e-6 * a11 * a22  # directions more than ~0.06 degrees apart
    det_safe = np.where(well_posed, det, 1.0)
    t1 = (a22 * b1 - a12 * b2) / det_safe
    t2 = (a11 * b2 - a12 * b1) / det_safe
    common = x1c + t1[:, None] * v1
    shift = np.where(converging[:, None], -common, 0.0)
    x1 = x1c + shift - spec.touch_time * v1
    x2 = x2c + shift - spec.touch_time * v2

    valid = (d1 > 0) & (d2 > 0) & (rho1 > 0) & (rho2 > 0)
    valid &= (g_norm * cos_a >= spec.min_normal_speed) & (g_norm * cos_a > 0)
    valid &= g_norm >= spec.min_relative_speed
    valid &= (offset == 0) | (p_norm > 1e-9 * np.maximum(g_norm, 1e-300) + 1e-12)
    valid &= ~converging | (well_posed & (t1 >= 0) & (t2 >= 0))
    return {"x1": x1, "x2": x2, "v1": v1, "v2": v2, "d1": d1, "d2": d2, "rho1": rho1, "rho2": rho2,
            "normal": normal, "offset": offset, "valid": valid}


_FIELDS = ("x1", "x2", "v1", "v2", "d1", "d2", "rho1", "rho2", "normal", "offset")


def _draw_block(spec: ConfigurationSpec, seed: int, block: int) -> dict:
    """All ``BLOCK_ROWS`` rows of block ``block`` (rejection sampling, deterministic)."""
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(block,)))
    weights = np.asarray(spec.family_weights, dtype=float)
    family = rng.choice(3, size=BLOCK_ROWS, p=weights / weights.sum()).astype(np.int8)
    kind = rng.random(BLOCK_ROWS)  # drawn once: redraws keep the fractions
    central = kind < spec.central_fraction
    grazing = ~central & (kind < spec.central_fraction + spec.grazing_fraction)
    slow = rng.random(BLOCK_ROWS) < spec.slow_fraction if spec.slow_fraction > 0 else np.zeros(BLOCK_ROWS, bool)
    rows: dict = {}
    todo = np.arange(BLOCK_ROWS)
    for _ in range(10_000):
        cand = _draw_candidates(spec, rng, family[todo], central[todo], grazing[todo], slow[todo])
        ok = cand.pop("valid")
        for name, values in cand.items():
            if name not in rows:
                rows[name] = np.zeros((BLOCK_ROWS,) + values.shape[1:], dtype=np.float64)
            rows[name][todo[ok]] = values[ok]
        todo = todo[~ok]
        if todo.size == 0:
            rows["family"] = family
            if spec.spin_fraction > 0:
                rows.update(_draw_spins(spec, seed, block, rows))
            return rows
    raise ConfigError("could not draw colliding configurations: min_normal_speed / min_relative_speed is too high "
                      "for the speed range")


def _draw_spins(spec: ConfigurationSpec, seed: int, block: int, rows: dict) -> dict:
    """Spins of the block's rows (``spin_fraction`` of them; a random stream of their own)."""
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(block, 1)))
    n = rows["v1"].shape[0]
    g = np.linalg.norm(rows["v1"] - rows["v2"], axis=1)
    spinning = rng.random(n) < spec.spin_fraction
    out = {}
    for k, d in (("omega1", rows["d1"]), ("omega2", rows["d2"])):
        axis = _direction(rng, n)
        surface = spec.spin_ratio * g * rng.random(n)
        out[k] = np.where(spinning[:, None], axis * (surface / (0.5 * d))[:, None], 0.0)
    return out


def generate(spec: ConfigurationSpec, seed: int, start: int, stop: int) -> Configurations:
    """Configurations ``start <= k < stop`` for ``seed``; row ``k`` never depends on ``start``/``stop``."""
    if not 0 <= start <= stop:
        raise ConfigError(f"need 0 <= start <= stop (got {start}, {stop})")
    if not 0 <= int(seed) < 2**63:
        raise ConfigError(f"seed must be a non-negative integer (got {seed})")
    if stop == start:
        empty = {name: np.zeros((0, 3) if name in ("x1", "x2", "v1", "v2", "normal") else (0,)) for name in _FIELDS}
        if spec.spin_fraction > 0:
            empty.update(omega1=np.zeros((0, 3)), omega2=np.zeros((0, 3)))
        return Configurations(config_id=np.zeros(0, dtype=np.int64), family=np.zeros(0, dtype=np.int8),
                              touch_time=spec.touch_time, **empty)
    first, last = start // BLOCK_ROWS, (stop - 1) // BLOCK_ROWS
    parts = [_draw_block(spec, int(seed), j) for j in range(first, last + 1)]
    lo = start - first * BLOCK_ROWS
    names = _FIELDS + ("family",) + (("omega1", "omega2") if spec.spin_fraction > 0 else ())
    cat = {name: np.concatenate([p[name] for p in parts])[lo:lo + stop - start] for name in names}
    return Configurations(config_id=np.arange(start, stop, dtype=np.int64), touch_time=spec.touch_time,
                          **{name: cat[name] for name in names})
