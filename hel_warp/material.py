"""Particle material and the DEM time step of the paper's eqs. (12)-(15).

Defaults are the paper's polyethylene microspheres (density 1000 kg/m^3, Cospheric).
Young's modulus 0.5 GPa and Poisson ratio 0.4 are our choice: polyethylene spans
E = 0.2 GPa (LDPE) to 1.1 GPa (HDPE) and nu = 0.40-0.46 (J. E. Mark, *Physical Properties
of Polymers Handbook*, 2nd ed., Springer 2007, ch. 21 and Table 21.1), and with E = 0.5 GPa,
nu = 0.4 eq. (12) gives 2.49e-7 s for a 315 um sphere, next to the paper's 2.46e-7 s.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from hel_warp.errors import ConfigError, require_finite, require_positive


@dataclass(frozen=True)
class TimeStep:
    """The three critical time steps of eqs. (13)-(15) and the chosen DEM step, eq. (12). Seconds."""

    rayleigh: float
    hertz: float
    cundall: float
    factor: float

    @property
    def chosen(self) -> float:
        """``factor * min(rayleigh, hertz, cundall)``, eq. (12) (factor 0.2 in the paper)."""
        return self.factor * min(self.rayleigh, self.hertz, self.cundall)

    def as_dict(self) -> dict:
        return {"rayleigh": self.rayleigh, "hertz": self.hertz, "cundall": self.cundall,
                "factor": self.factor, "chosen": self.chosen}


@dataclass(frozen=True, kw_only=True)
class Material:
    """Elastic and frictional properties of one particle material (SI units).

    Validated at construction; every error says which field to change.
    """

    density: float = 1000.0
    """Material density rho_p, kg/m^3."""
    youngs_modulus: float = 5.0e8
    """Young's modulus E, Pa."""
    poisson_ratio: float = 0.4
    """Poisson ratio nu, in (-1, 0.5)."""
    restitution: float = 0.9
    """Normal restitution coefficient e of particle-particle impacts, in (0, 1] (Table 1: e_ss = 0.9)."""
    friction: float = 0.3
    """Sliding (Coulomb) friction coefficient mu >= 0."""
    rolling_friction: float = 0.0
    """Rolling friction coefficient (dimensionless, constant-torque model), >= 0; 0 switches it off."""
    wall_restitution_normal: float = 0.8
    """Normal reflection coefficient of parcels at walls (HEL, Table 1: 0.8)."""
    wall_restitution_tangential: float = 0.8
    """Tangential reflection coefficient of parcels at walls (HEL, Table 1: 0.8)."""

    def __post_init__(self) -> None:
        for name in ("density", "youngs_modulus", "poisson_ratio", "restitution", "friction",
                     "rolling_friction", "wall_restitution_normal", "wall_restitution_tangential"):
            require_finite(f"material {name}", getattr(self, name))
        require_positive("material density", self.density, "kg/m^3")
        require_positive("material youngs_modulus", self.youngs_modulus, "Pa")
        if not -1.0 < self.poisson_ratio < 0.5:
            raise ConfigError(f"material poisson_ratio must lie in (-1, 0.5) (got {self.poisson_ratio}); "
                              "0.3-0.45 is typical for polymers")
        if not 0.0 < self.restitution <= 1.0:
            raise ConfigError(f"material restitution must lie in (0, 1] (got {self.restitution})")
        if self.friction < 0.0:
            raise ConfigError(f"material friction must be >= 0 (got {self.friction})")
        if self.rolling_friction < 0.0:
            raise ConfigError(f"material rolling_friction must be >= 0 (got {self.rolling_friction})")
        for name in ("wall_restitution_normal", "wall_restitution_tangential"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ConfigError(f"material {name} must lie in [0, 1] (got {value})")

    @property
    def shear_modulus(self) -> float:
        """G = E / (2 (1 + nu)), Pa."""
        return self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))

    def as_dict(self) -> dict:
        return asdict(self)

    def time_step(self, radius: float, *, max_speed: float = 20.0, normk: float = 0.001,
                  factor: float = 0.2) -> TimeStep:
        """Critical DEM time steps for a sphere of ``radius`` (m), eqs. (12)-(15).

        - Rayleigh (LIGGGHTS docs; the paper's eq. (13) misprints the bracket):
          ``pi r / (0.1631 nu + 0.8766) * sqrt(rho / G)``;
        - Hertz, eq. (14): ``2.87 [ (rho 4/3 pi r^3)^2 / (r E^2 V_max) ]^0.2``;
        - Cundall (LS-DYNA DEM), eq. (15): ``sqrt(rho 4/3 pi r^2 / (E / (3 (1 + nu)) NORMK))``;
        - chosen, eq. (12): ``0.2 min(...)``.
        ``max_speed`` is V_max (m/s) of eq. (14); ``normk`` the LS-DYNA penalty (paper: 0.001).
        """
        require_positive("radius", radius, "m")
        require_positive("max_speed", max_speed, "m/s")
        require_positive("normk", normk)
        if not 0.0 < factor <= 1.0:
            raise ConfigError(f"time-step factor must lie in (0, 1] (got {factor})")
        rho, E, nu = self.density, self.youngs_modulus, self.poisson_ratio
        rayleigh = math.pi * radius / (0.1631 * nu + 0.8766) * math.sqrt(rho / self.shear_modulus)
        mass = rho * 4.0 / 3.0 * math.pi * radius**3
        hertz = 2.87 * (mass**2 / (radius * E**2 * max_speed)) ** 0.2
        cundall = math.sqrt(rho * 4.0 / 3.0 * math.pi * radius**2 / (E / (3.0 * (1.0 + nu)) * normk))
        return TimeStep(rayleigh=rayleigh, hertz=hertz, cundall=cundall, factor=factor)

    def check_time_step(self, dt: float, radius: float, *, max_speed: float = 20.0) -> None:
        """Raise ConfigError when ``dt`` exceeds the stable DEM step of eq. (12) for ``radius``."""
        require_positive("time step dt", dt, "s")
        stable = self.time_step(radius, max_speed=max_speed).chosen
        if dt > stable * (1.0 + 1e-9):
            raise ConfigError(f"time step dt = {dt:.3e} s is above the stable DEM step {stable:.3e} s "
                              f"of eq. (12) for radius {radius:.3e} m; use --dt {stable:.3e} or smaller")


POLYETHYLENE = Material()
"""The paper's polyethylene microspheres (see the module docstring for the sources)."""
