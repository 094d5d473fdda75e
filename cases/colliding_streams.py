"""Colliding particle streams: the lab rig of the paper (sections 2, 5, 8; Figs. 1 and 10).

Two side arms carry polyethylene particles into a main channel, where the two streams collide;
particle velocity profiles are measured in ten sections downstream of the junction
(``hel-warp report`` post-processes the run directory this script writes).

Geometry (all assumed dimensions are named in :class:`RigDimensions` with the reason). Axes:
x = main-channel axis (downstream = +x), y = across the channel (the width the camera sees and
the direction the velocity profiles run along), z = depth (camera viewing direction)::

        y
        ^  left supply ==========\\               (stream 0, inlet on x = 0)
        |                          \\  arm at 45 deg
        |  main ==================================|S1|..|S10|==> outlet (x = 160 mm, p' = 0)
        |                          //
        |  right supply =========//               (stream 1, inlet on x = 0)

- main channel 20 mm x 10 mm (2.0e-4 m^2 = 240 l/min / 20 m/s), inlet on x = 0 at 240 l/min;
- two side supply channels 4 mm x 8 mm (3.2e-5 m^2 = 38.4 l/min / 20 m/s), inlets on x = 0 at
  38.4 l/min each, turning into arms inclined at 45 deg that open into the main channel;
- grid h = 1 mm: 160 x 64 x 10 = 102,400 cells (the paper's mesh: 107,000 hexahedra);
- ten measurement sections (boxes 8 mm long, full width and depth) downstream of the junction;
- a volume-injection box in each supply channel releases parcels at 3.4 m/s along the channel
  (the speed the paper's DEM run of the particle holder gave), at the experimental mass flow
  rates per holder, until each holder has released half of the particles.

Inlet speeds are set so that the discrete patch (faces x h^2) carries exactly the paper's volume
flow; on the default grid every patch is aligned with the grid, so the speed is exactly 20 m/s.
``--cells N`` shrinks the grid for CI: h grows as (102400/N)^(1/3), and a cross-section side
narrower than 3 h is widened to 3 h (the flows stay 240 / 38.4 l/min, the speed drops).

Usage::

    python cases/colliding_streams.py --diameter 315e-6 --dt 1e-3 --collisions ktgf \
        --end-time 0.02 --out runs/cs_ktgf_1e-3
    python cases/colliding_streams.py --diameter 315e-6 --dt 1e-3 --collisions none \
        --end-time 0.003 --cells 5000 --max-particles 200 --out runs/ci    # reduced rig
    hel-warp run colliding_streams --diameter 315e-6 --dt 1e-3 --collisions surrogate --end-time 0.02 --out runs/cs

A binary mixture: ``--diameter 315e-6 --diameter2 475e-6 --mass-fraction2 0.5`` (``mixture_release``): both
holders release both sizes over one window each, the total mass that of the paper's one-size runs (0.196 g,
12,000 particles of 315 um; the experiment's 21 g would be ~1.3 million particles) split by mass between the
species (50/50: 6,000 + 1,742 parcels) and evenly between the holders, each holder's mass flow the mass-fraction mix
of the paper's measured flows of the two sizes; ``ktgf`` gets the mixture's Sauter mean diameter (the mixture KTGF
closures are out of scope); a surrogate model must hold both sizes and their ratios in its training domain. The rig
layout names the ``size_classes``, and ``hel-warp report`` gives the profiles and stream metrics per size class
beside the whole run. ``--particles-per-parcel W1,W2`` gives each species its own weight (one value: both): the real
mass and its split stay, each species releases real / W_k parcels (50/50 at 1,8: 6,000 + 218 parcels), the release
window is the holder's real mass over its mass flow, and the cell detection (the default when a weight exceeds 1)
collides them at the real number density. (One size keeps the parcel count and scales the mass with W.)

The rig is a flow of the case API (``hel_warp.case``): its shapes, inlets, outlet, injectors and gas warm-up
described in :func:`build`, the step (``HelSolver.step``: deposit, gas, interpolate, collide, push, outlets,
walls with e_n = e_t = 0.8, scheduled injection) and the outputs those of every case: ``OUT/run.zarr``
(particle snapshots with x, v, radius, weight, stream, particle_id; gas fields; series ``timing_step``,
``timing_<sub-step>``, ``collisions_<kind>``), VTK files, checkpoints (``--resume`` continues from the last
one) and ``summary.json`` (``--json`` prints it). The case adds attrs ``config.case`` (the settings, the grid
and the rig layout ``rig``: sections and axes, which ``hel-warp report`` reads) and the summary's
``collisions``, ``diameter``, ``total_collisions``, ``check_errors``. ``check()`` verifies physical facts at
the end (no parcel centre inside a wall, parcels alive = injected - removed).

Further assumptions: gravity along +x (the rig upright, flow downwards, holders above the arms);
the gas runs alone for ``--gas-warmup`` (0.01 s) before the release ("once the flow is
stabilized", section 2); diameters normal with the paper's sigma (8.2 / 22 um), truncated at 3 sigma.
"""

from __future__ import annotations

import math
import sys
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(REPO))

from hel_warp import case as hc  # noqa: E402

LITRE_PER_MIN = 1.0e-3 / 60.0
"""1 l/min in m^3/s."""

COLLISIONS = ("none", "ktgf", "surrogate", "surrogate-paper", "dem")

PAPER_PARTICLES = {315e-6: 12000, 475e-6: 3600}
"""Particles injected in the paper's runs (section 8), both holders together, one particle per parcel."""
PAPER_DIAMETER_STD = {315e-6: 8.2e-6, 475e-6: 22e-6}
"""Standard deviation of the measured size distributions (section 2), m."""
PAPER_MASS_FLOW = {315e-6: (0.014, 0.018), 475e-6: (0.013, 0.019)}
"""Measured mass flow rates of the left / right holder (section 2), kg/s."""
DEFAULT_MASS_FLOW = (0.014, 0.018)


@dataclass(frozen=True, kw_only=True)
class RigDimensions:
    """Every assumed dimension of the rig, m (the paper gives flows, speeds and the mesh size, not the drawing)."""

    main_flow: float = 240.0 * LITRE_PER_MIN
    """Main inlet volume flow, m^3/s (paper section 2: 240 l/min)."""
    side_flow: float = 38.4 * LITRE_PER_MIN
    """Volume flow of each side inlet, m^3/s (paper section 2: 38.4 l/min)."""
    supply_speed: float = 20.0
    """Gas speed in every supply channel, m/s (paper section 2); sets the cross-sections."""
    main_width: float = 20.0e-3
    """Main channel width (y), m. With main_depth: 2.0e-4 m^2 = 240 l/min / 20 m/s; a 2:1 flat core, seen by
    the camera across its width (assumed aspect ratio)."""
    main_depth: float = 10.0e-3
    """Main channel depth (z, viewing direction), m (see main_width)."""
    side_width: float = 4.0e-3
    """Side arm width (in the x-y plane), m. With side_depth: 3.2e-5 m^2 = 38.4 l/min / 20 m/s (assumed 1:2)."""
    side_depth: float = 8.0e-3
    """Side arm depth (z), m, centred in the main channel's depth (see side_width)."""
    main_length: float = 160.0e-3
    """Main channel length from the inlet plane (x = 0) to the outlet, m: 40 mm of main supply before the
    junction, the collision region, the ten sections and 10 mm before the outlet (assumed)."""
    supply_length: float = 20.0e-3
    """Straight part of each side arm from the inlet plane, m: holds the injection box (assumed)."""
    side_offset: float = 30.0e-3
    """Distance of the side supply channels' axes from the main axis, m: with a 45 deg arm the arm axis meets the
    main-channel wall 20 mm downstream of the supply channel (assumed)."""
    arm_angle_deg: float = 45.0
    """Inclination of the arms to the main axis, deg (assumed; the paper's drawing shows inclined arms)."""
    arm_overlap: float = 3.0e-3
    """How far each arm extends past the main-channel wall into the main channel, m (so the union of shapes is
    connected; inside the main channel it changes nothing)."""
    spacing: float = 1.0e-3
    """Default grid spacing, m: all the sizes above are multiples of it, so every patch is grid-aligned and
    160 x 64 x 10 = 102,400 cells (the paper's mesh had 107,000 hexahedra)."""
    section_first: float = 55.0e-3
    """x of the centre of the first measurement section, m (downstream of the junction: the arm axes cross
    the main axis at x = 48 mm)."""
    section_pitch: float = 10.0e-3
    """Distance between section centres, m (ten sections, last centre at 145 mm)."""
    section_length: float = 8.0e-3
    """Length of each section box along x, m; each spans the full width and depth (assumed)."""
    injection_x: tuple = (2.0e-3, 18.0e-3)
    """x-range of the injection boxes inside the supply channels, m (assumed): nearly the whole 20 mm straight
    part, so that the released parcels (0.014-0.019 kg/s, a mass loading of ~18 on the arm's gas) start at
    eps_s ~ 0.05 rather than piling up in a small box (the explicit drag source of the gas step needs
    rho_p eps_s F_D dt / rho_f below ~1)."""
    injection_speed: float = 3.4
    """Initial particle speed along the supply channel, m/s (paper section 5: DEM of the particle holder)."""

    @property
    def main_area(self) -> float:
        return self.main_width * self.main_depth

    @property
    def side_area(self) -> float:
        return self.side_width * self.side_depth

    def side_centre_y(self, side: int) -> float:
        """y of the supply channel axis of arm ``side`` (0 = left, +y; 1 = right, -y)."""
        return self.side_offset if side == 0 else -self.side_offset

    def domain(self) -> tuple:
        """(lo, hi) of the grid box, m."""
        half_y = self.side_offset + 0.5 * self.side_width
        return (0.0, -half_y, 0.0), (self.main_length, half_y, self.main_depth)

    def sections(self) -> list:
        """The ten measurement boxes: dicts name, lo, hi (m)."""
        out = []
        for i in range(10):
            xc = self.section_first + i * self.section_pitch
            out.append({"name": f"S{i + 1}",
                        "lo": [xc - 0.5 * self.section_length, -0.5 * self.main_width, 0.0],
                        "hi": [xc + 0.5 * self.section_length, 0.5 * self.main_width, self.main_depth]})
        return out

    def arm_axis(self, side: int) -> tuple:
        """(start, end) of the inclined arm's axis, m: from inside the supply channel to past the main wall."""
        angle = math.radians(self.arm_angle_deg)
        sign = 1.0 if side == 0 else -1.0
        zc = 0.5 * self.main_depth
        x0 = self.supply_length - 0.5 * self.side_width
        y0 = sign * self.side_offset
        drop = self.side_offset - 0.5 * self.main_width + self.arm_overlap  # lateral travel of the axis
        x1 = x0 + drop / math.tan(angle)
        y1 = sign * (self.side_offset - drop)
        return (x0, y0, zc), (x1, y1, zc)

    def injection_box(self, side: int, margin: float) -> tuple:
        """(lo, hi) of the injection box of arm ``side``; ``margin`` (m, a particle radius) from the walls."""
        yc = self.side_centre_y(side)
        zc = 0.5 * self.main_depth
        return ((self.injection_x[0], yc - 0.5 * self.side_width + margin, zc - 0.5 * self.side_depth + margin),
                (self.injection_x[1], yc + 0.5 * self.side_width - margin, zc + 0.5 * self.side_depth - margin))


def dimensions_for_cells(cells: int | None) -> RigDimensions:
    """The rig for a grid of about ``cells`` cells (None: the default 102,400-cell grid).

    A coarser grid has h = 1 mm x (102400/cells)^(1/3); a cross-section side narrower than 3 h is
    widened to 3 h (grid.MIN_CELLS_ACROSS) and the section boxes keep their places.
    """
    dims = RigDimensions()
    if cells is None:
        return dims
    if int(cells) != cells or cells < 1000:
        from hel_warp.errors import ConfigError

        raise ConfigError(f"--cells must be an integer >= 1000 (got {cells!r})")
    lo, hi = dims.domain()
    default_cells = np.prod([round((h - l) / dims.spacing) for l, h in zip(lo, hi)])
    h = dims.spacing * (default_cells / cells) ** (1.0 / 3.0)
    if h <= dims.spacing:
        return replace(dims, spacing=h)
    least = 3.0 * h * (1.0 + 1e-6)
    return replace(dims, spacing=h, main_depth=max(dims.main_depth, least), side_width=max(dims.side_width, least),
                   side_depth=max(dims.side_depth, least))



def rig_shapes(dims: RigDimensions) -> tuple:
    """The fluid region: the main channel, two supply channels and two inclined arms (a union of shapes that runs
    past the inlet and outlet planes, so that no wall stands on an open boundary)."""
    from hel_warp.gas.grid import Box, Channel

    h = dims.spacing
    beyond = 5.0 * h
    zc = 0.5 * dims.main_depth
    shapes = [Box(lo=(-beyond, -0.5 * dims.main_width, 0.0),
                  hi=(dims.main_length + beyond, 0.5 * dims.main_width, dims.main_depth), name="main")]
    for side, label in ((0, "left"), (1, "right")):
        yc = dims.side_centre_y(side)
        shapes.append(Box(lo=(-beyond, yc - 0.5 * dims.side_width, zc - 0.5 * dims.side_depth),
                          hi=(dims.supply_length, yc + 0.5 * dims.side_width, zc + 0.5 * dims.side_depth),
                          name=f"{label}_supply"))
        start, end = dims.arm_axis(side)
        shapes.append(Channel(start=start, end=end, width=dims.side_width, height=dims.side_depth,
                              up=(0.0, 0.0, 1.0), name=f"{label}_arm"))
    return tuple(shapes)


def add_boundaries(flow, dims: RigDimensions) -> None:
    """Three inlets on x = 0 at the paper's volume flows (the speed is the flow over the discrete patch area) and
    the outlet at x = main_length; parcels leave through both ends."""
    big = 1.0
    flow.inlet("main_inlet", "x-", flow_rate=dims.main_flow, lo=(-big, -0.5 * dims.main_width, -big),
               hi=(big, 0.5 * dims.main_width, big), particles="remove")
    for name, yc in (("left_inlet", dims.side_offset), ("right_inlet", -dims.side_offset)):
        flow.inlet(name, "x-", flow_rate=dims.side_flow, lo=(-big, yc - 0.5 * dims.side_width, -big),
                   hi=(big, yc + 0.5 * dims.side_width, big), particles="remove")
    flow.outlet("outlet", "x+", pressure=0.0)


def rig_flow(dims: RigDimensions, gravity=(9.80665, 0.0, 0.0), warmup: float = 0.0):
    lo, hi = dims.domain()
    flow = hc.Flow("colliding_streams", lo=lo, hi=hi, spacing=dims.spacing, gravity=gravity,
                   gas=hc.Gas(warmup=warmup), shapes=rig_shapes(dims))
    add_boundaries(flow, dims)
    return flow


def build_geometry(dims: RigDimensions):
    """(Grid, Geometry, inlet speeds {patch: m/s}) of the rig; speeds make patch area x speed = the paper's flow."""
    from hel_warp.case.build import geometry_of, grid_of

    flow = rig_flow(dims)
    grid = grid_of(flow)
    geometry, _, speeds = geometry_of(flow, grid)
    return grid, geometry, speeds


# ---------------------------------------------------------------------------------------------- the case
@dataclass(frozen=True, kw_only=True)
class CaseConfig:
    """The rig's own settings of one run (validated by :func:`make_config`; the shared ones are the case API's)."""

    diameter: float
    """Mean particle diameter, m (paper: 315e-6 or 475e-6)."""
    dt: float
    """HEL time step, s (paper: 1e-3, 1e-4, 7.14e-5)."""
    collisions: str
    """Collision model: none, ktgf, surrogate, surrogate-paper, dem."""
    particle_contacts: bool = True
    """``dem`` only: False switches the particle-particle contacts off (walls, drag, injection unchanged): the
    like-with-like run that, beside ``none``, shows how much of a gap the walls alone make."""
    particles_per_parcel: float = 1.0
    """Real particles per parcel of the (first) species (paper's second HEL run: 8). One size: the parcel count
    stays, the mass scales; a mixture: the real mass stays (:func:`mixture_release`), parcels = real / weight."""
    particles_per_parcel2: float | None = None
    """A mixture: real particles per parcel of the second species (``--particles-per-parcel W1,W2``)."""
    particles: int = 12000
    """Parcels released, both holders together (paper: 12,000 at 315 um, 3,600 at 475 um)."""
    diameter_std: float = 0.0
    """Standard deviation of the diameter, m (paper: 8.2 um / 22 um)."""
    density: float = 1000.0
    """Particle density, kg/m^3 (polyethylene, paper section 2)."""
    mass_flow: tuple = DEFAULT_MASS_FLOW
    """Release rate of the left / right holder, kg/s of real particles (paper section 2)."""
    cells: int | None = None
    """Grid size (None: the default 102,400 cells)."""
    gas_warmup: float = 0.01
    """Gas-only time before the release (1e-3 s steps), s: "once the flow is stabilized" (section 2);
    0.01 s at 20 m/s flushes the 160 mm rig 1.25 times."""
    model: str | None = None
    """Surrogate model directory (surrogate and surrogate-paper)."""
    detection: str = "swept"
    """``surrogate`` pair detection: ``swept`` (continuous, default), ``overlap`` (the paper's end-of-step test) or
    ``cell`` (stochastic per collision cell, the default with ``particles_per_parcel`` > 1)."""
    wall_contact: str = "surface"
    """Where HEL parcels meet the walls: ``surface`` (default: a particle radius from the centre, as the ``dem``
    spheres, so that HEL and its reference share the walls' geometry) or ``point`` (their centre, MP-PIC)."""
    wall_spin: bool = False
    """HEL parcels meet the walls as rough spheres that carry their spin, as the ``dem`` spheres roll; False: the
    spinless reflection with Table 1's e_t = 0.8."""
    particle_spin: bool = False
    """``surrogate`` (pairwise): collisions at the contact point, the spins turned."""
    seed: int = 0
    device: str = "cpu"
    gravity: tuple = (9.80665, 0.0, 0.0)
    """m/s^2: the rig stands upright with the flow downwards (+x), holders above the arms (assumed)."""
    diameter2: float | None = None
    """A binary mixture: mean diameter of the second species, m (None: one size). Both holders release both
    species (:func:`mixture_release`)."""
    diameter2_std: float = 0.0
    """Standard deviation of the second species' diameter, m."""
    mass_fraction2: float = 0.0
    """Mass fraction of the second species in every holder (0: one size)."""
    particles2: int = 0
    """Parcels of the second species released, both holders together (``particles`` counts the first)."""
    release_weight: float = 1.0
    """One size: the real particles each parcel counts in the holders' release window (``--real-particles``:
    paper parcels / parcels, so that any number of real particles leaves over the paper's window; 1: the
    window of the paper's parcels of one particle, whatever the weight)."""

    @property
    def mixture(self) -> bool:
        return self.diameter2 is not None

    def species(self) -> list:
        """(diameter, std, parcels) of each species released."""
        out = [(self.diameter, self.diameter_std, self.particles)]
        if self.mixture:
            out.append((self.diameter2, self.diameter2_std, self.particles2))
        return out

    def weights(self) -> list:
        """Real particles per parcel of each species released."""
        if not self.mixture:
            return [self.particles_per_parcel]
        return [self.particles_per_parcel, self.particles_per_parcel2]

    def release_weights(self) -> list:
        """Per species, the weight the holders' mass (and so the release window) counts: a mixture's real mass
        (its weights), one size's parcels of one particle (the mass flow scales with the weight, as before)."""
        return self.weights() if self.mixture else [self.release_weight]


def make_config(args) -> CaseConfig:
    """The rig's options, checked (a ConfigError names what to change)."""
    from hel_warp.errors import ConfigError
    from hel_warp.collisions.mixture import species_weights

    if not args.diameter > 0:
        raise ConfigError(f"--diameter must be > 0 m (got {args.diameter}); e.g. 315e-6")
    if not args.dt > 0:
        raise ConfigError(f"--dt must be > 0 s (got {args.dt})")
    two_sizes = getattr(args, "diameter2", None) is not None or getattr(args, "mass_fraction2", None) is not None
    weights = species_weights(args.particles_per_parcel, 2 if two_sizes else 1)
    known = min(PAPER_PARTICLES, key=lambda d: abs(d - args.diameter))
    paper_size = abs(known - args.diameter) < 1e-3 * known
    particles = PAPER_PARTICLES[known] if paper_size else int(round(12000 * (315e-6 / args.diameter) ** 3))
    release_weight = 1.0
    real = getattr(args, "real_particles", None)
    if real is not None:
        if two_sizes:
            raise ConfigError("--real-particles is a one-size option (a mixture keeps the paper's real mass); drop "
                              "it or --diameter2")
        if not real >= 2 * weights[0]:
            raise ConfigError(f"--real-particles must be >= 2 x --particles-per-parcel (got {real}); e.g. 96000 "
                              "(the paper's second HEL run, 0.0016 kg at 315 um)")
        # the holders release `real` particles over the paper's window (the paper's parcel count, one particle
        # each): the mass flow scales with real / paper, as the paper's second run (8 x the mass, same parcels)
        parcels = max(2, int(round(real / weights[0])))
        release_weight = particles / parcels
        particles = parcels
    if args.max_particles is not None:
        if args.max_particles < 2:
            raise ConfigError(f"--max-particles must be >= 2 (got {args.max_particles})")
        particles = min(particles, int(args.max_particles))
    std = PAPER_DIAMETER_STD[known] if paper_size else 0.0
    if args.monodisperse:
        std = 0.0
    if args.no_particle_contacts and args.collisions != "dem":
        raise ConfigError(f"--no-particle-contacts is a dem option (got --collisions {args.collisions}); none "
                          "already has no particle-particle collisions")
    if getattr(args, "wall_spin", False) and args.collisions == "dem":
        raise ConfigError("--wall-spin is a HEL option; the dem's spheres roll on the walls on their own")
    detection = getattr(args, "detection", None)
    mixture = mixture_release(args, args.diameter, std, known if paper_size else None, weights)
    if mixture is not None:
        particles = mixture.pop("particles")
        mass_flow = mixture.pop("mass_flow")
    else:
        mass_flow = PAPER_MASS_FLOW[known] if paper_size else DEFAULT_MASS_FLOW
        mixture = {}
    return CaseConfig(diameter=float(args.diameter), dt=float(args.dt), collisions=args.collisions,
                      particles_per_parcel=float(weights[0]), particle_contacts=not args.no_particle_contacts,
                      particles=particles, diameter_std=std, **mixture, release_weight=release_weight,
                      mass_flow=mass_flow, cells=args.cells, gas_warmup=float(args.gas_warmup), model=args.model,
                      detection=detection or ("cell" if max(weights) > 1 else "swept"),
                      wall_contact=getattr(args, "wall_contact", "surface"),
                      wall_spin=bool(getattr(args, "wall_spin", False)),
                      particle_spin=bool(getattr(args, "particle_spin", False)),
                      seed=int(args.seed), device=args.device)


def sauter_mean_of(config: CaseConfig) -> float:
    """The one diameter KTGF gets: the mean diameter, or a mixture's Sauter mean d_32 = sum N E[d^3] / sum N E[d^2]
    (the mixture KTGF closures are out of scope)."""
    from hel_warp.collisions.mixture import sauter_mean

    if not config.mixture:
        return config.diameter
    species = config.species()  # number fractions of the real particles: parcels x weight
    return sauter_mean([n * w for (_, _, n), w in zip(species, config.weights())], [d for d, _, _ in species],
                       [sd for _, sd, _ in species])


def mixture_release(args, diameter: float, std: float, known: float | None, weights=(1, 1)) -> dict | None:
    """The release of a binary mixture (--diameter2 with --mass-fraction2), or None for one size.

    Total mass: that of the paper's one-size runs, 12,000 particles of 315 um (0.196 g, section 8; the 21 g
    of the experiment's holders would be ~1.3 million particles), split by mass (1 - F, F) between the species
    and evenly between the holders, each holder releasing both species at once. Real particles per species:
    mass / mean particle mass; parcels per species: real / weight (``weights`` (W1, W2), rounded, at least 2), so
    the real mass stays whatever the weights; --max-particles caps the parcels in total, both species scaled
    alike. Each holder's mass flow is the mass-fraction mix of the paper's measured flows of the two sizes
    (0.014/0.018 kg/s at 315 um, 0.013/0.019 at 475 um). Returns the ``CaseConfig`` fields ``particles``,
    ``particles2`` (parcels), ``particles_per_parcel2``, ``diameter2``, ``diameter2_std``, ``mass_fraction2``,
    ``mass_flow``."""
    from hel_warp.errors import ConfigError

    from hel_warp.collisions.mixture import second_size

    sizes = second_size(getattr(args, "diameter2", None), getattr(args, "mass_fraction2", None), diameter,
                        "--mass-fraction2", "0.5")
    if sizes is None:
        return None
    d2, f2 = sizes
    known2 = min(PAPER_PARTICLES, key=lambda d: abs(d - d2))
    paper2 = abs(known2 - d2) < 1e-3 * known2
    std2 = 0.0 if args.monodisperse else (PAPER_DIAMETER_STD[known2] if paper2 else 0.0)
    mean_cube = lambda d, sd: d**3 + 3.0 * d * sd**2  # noqa: E731  E[d^3] of a normal size distribution
    total = PAPER_PARTICLES[315e-6] * mean_cube(315e-6, PAPER_DIAMETER_STD[315e-6])  # in units of pi rho / 6
    w1, w2 = (float(w) for w in weights)
    n1 = max(2, int(round((1.0 - f2) * total / mean_cube(diameter, std) / w1)))
    n2 = max(2, int(round(f2 * total / mean_cube(d2, std2) / w2)))
    if args.max_particles is not None:
        if args.max_particles < 4:
            raise ConfigError(f"--max-particles must be >= 4 for a mixture (got {args.max_particles})")
        scale = min(1.0, args.max_particles / (n1 + n2))
        n1, n2 = max(2, int(round(n1 * scale))), max(2, int(round(n2 * scale)))
    flow1 = PAPER_MASS_FLOW[known] if known is not None else DEFAULT_MASS_FLOW
    flow2 = PAPER_MASS_FLOW[known2] if paper2 else DEFAULT_MASS_FLOW
    flow = tuple((1.0 - f2) * a + f2 * b for a, b in zip(flow1, flow2))
    return {"particles": n1, "particles2": n2, "particles_per_parcel2": w2, "diameter2": float(d2),
            "diameter2_std": float(std2), "mass_fraction2": float(f2), "mass_flow": flow}


def holder_release(config: CaseConfig):
    """Per holder: each species' parcels (left, right), and the holder's release window, s. Each holder releases
    half of the parcels at its measured mass flow (section 2): a window of (parcels x particle mass) / mass flow, for
    one size the same for any particles-per-parcel (the parcel count stays); a mixture: every holder releases half
    of each species, all species over the holder's one window of its real mass."""
    species = config.species()
    mass_weights = config.release_weights()
    split = [(n // 2, n - n // 2) for _, _, n in species]  # per species: (left, right) parcels
    windows = []
    for side in (0, 1):
        holder_mass = sum(split[k][side] * mass_weights[k] * config.density * math.pi / 6.0
                          * (d**3 + 3.0 * d * sd**2) for k, (d, sd, _) in enumerate(species))
        windows.append(holder_mass / config.mass_flow[side])
    return split, windows


def build(args):
    """The rig as a flow (the options checked by :func:`make_config`)."""
    config = make_config(args)
    args._rig = config
    return flow_of(config)


def flow_of(config: CaseConfig):
    """The rig as a flow: geometry, inlets, outlet, gravity, the two holders' injectors, the gas warm-up."""
    dims = dimensions_for_cells(config.cells)
    flow = rig_flow(dims, gravity=config.gravity, warmup=config.gas_warmup)
    flow.walls = hc.Walls(contact=config.wall_contact, spin=config.wall_spin)
    material = hc.Material(density=config.density)
    species = config.species()
    weights = config.weights()
    for k, (d, sd, _) in enumerate(species):
        flow.species(f"d{k + 1}", d, diameter_std=sd, material=material, weight=weights[k])
    split, windows = holder_release(config)
    margin = max(0.5 * d + 1.5 * sd for d, sd, _ in species)
    for side in (0, 1):
        lo, hi = dims.injection_box(side, margin)
        for k in range(len(species)):
            flow.inject(f"d{k + 1}", (lo, hi), count=split[k][side], start=0.0, end=windows[side],
                        speed=dims.injection_speed, direction=(1.0, 0.0, 0.0), stream=side,
                        seed=config.seed + 1000 * k)
    flow.collision_defaults["ktgf"] = {"particle_diameter": sauter_mean_of(config)}
    flow.collision_defaults["surrogate"] = {"detection": config.detection}
    flow.attrs = rig_attrs(flow, dims, config, windows)
    return flow


def rig_layout(dims: RigDimensions, config: CaseConfig) -> dict:
    """What the report needs to know about the rig (stored in the run's attrs)."""
    lo, hi = dims.domain()
    return {"axial_axis": 0, "transverse_axis": 1, "depth_axis": 2, "downstream": [1.0, 0.0, 0.0],
            "sections": dims.sections(), "domain_lo": list(lo), "domain_hi": list(hi),
            "main_width": dims.main_width, "main_depth": dims.main_depth,
            "streams": {"0": "left", "1": "right"}, "axis_transverse": 0.0,
            "stream_sides": {"0": 1.0, "1": -1.0},  # sign of y - axis on each stream's own arm (left = +y)
            "dimensions": asdict(dims),
            "size_classes": [{"diameter": d, "diameter_std": sd, "parcels": n, "particles_per_parcel": w}
                             for (d, sd, n), w in zip(config.species(), config.weights())]
            if config.mixture else None}


def rig_attrs(flow, dims: RigDimensions, config: CaseConfig, windows) -> dict:
    """The rig's settings stored with the run (``config.case``, which ``hel-warp report`` reads)."""
    from hel_warp.case.build import geometry_of, grid_of

    grid = grid_of(flow)
    _, _, speeds = geometry_of(flow, grid)
    from hel_warp.runs.io import _jsonable

    settings = asdict(config)
    return _jsonable({**settings, "grid_shape": list(grid.shape), "grid_cells": int(np.prod(grid.shape)),
                      "spacing": grid.spacing, "inlet_speeds": speeds,
                      "inlet_flows_l_per_min": {"main": dims.main_flow / LITRE_PER_MIN,
                                                "side": dims.side_flow / LITRE_PER_MIN},
                      "release_window_s": list(windows), "rig": rig_layout(dims, config)})


class CollidingStreams:
    """The rig built for ``config`` through the case API (for scripts and tests that step it by hand):
    ``solver`` (the HEL solver), ``pool``, ``collision``, ``grid``, ``geometry``, ``domain``, ``dims``,
    ``inlet_speeds``, ``release_window``, ``holder_parcels``, ``injector_side``; :func:`check` the physical facts."""

    def __init__(self, config: CaseConfig, *, model: str | None = None):
        from hel_warp.case.build import Settings, build as build_simulation

        flow = flow_of(config)
        settings = Settings(collisions=config.collisions, dt=config.dt, seed=config.seed, device=config.device,
                            model=model or config.model, particle_spin=config.particle_spin,
                            particle_contacts=config.particle_contacts)
        self.sim = build_simulation(flow, settings)
        self.config = config
        self.flow = flow
        self.dims = dimensions_for_cells(config.cells)
        self.solver = self.sim.solver
        self.pool = self.solver.pool
        self.collision = self.solver.collision
        self.grid, self.geometry, self.domain = self.sim.grid, self.sim.geometry, self.sim.domain
        self.gas_solver, self.gas = self.solver.gas_solver, self.solver.gas
        self.inlet_speeds = self.sim.inlet_speeds
        split, self.release_window = holder_release(config)
        self.holder_parcels = tuple(sum(s[side] for s in split) for side in (0, 1))
        self.injector_side = [side for side in (0, 1) for _ in config.species()]
        self.ktgf_diameter = sauter_mean_of(config)

    @property
    def fluid_cells(self) -> int:
        return self.sim.fluid_cells

    @property
    def injected(self) -> int:
        return int(sum(entry["count"] for entry in self.solver.injected()))

    def warm_up(self) -> int:
        return self.sim.warm_up()

    def step(self) -> dict:
        self.solver.step()
        return self.solver.collision_counts()

    def rig_layout(self) -> dict:
        return rig_layout(self.dims, self.config)


def check(rig) -> list[str]:
    """Physical facts at the end of the run; the list of violations (empty = pass).

    - no live parcel centre lies in a wall (SDF > 0; MP-PIC parcels meet the wall as points, so a centre may
      sit on it) and every position / velocity is finite;
    - parcels alive = parcels injected - parcels removed at the outlets;
    - every holder released no more than its share.
    """
    import warp as wp

    from kernels.sdf import eval_sdf

    solver = rig.solver
    config = rig.config if isinstance(rig, CollidingStreams) else rig.args._rig
    errors = []
    p = solver.pool.particles
    alive = p.alive.numpy().astype(bool)
    x = p.x.numpy()[alive]
    v = p.v.numpy()[alive]
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v))):
        errors.append("non-finite parcel positions or velocities")
    if x.shape[0]:
        geometry = solver.gas.domain.geometry
        points = wp.array(x, dtype=wp.vec3, device="cpu")
        distance = wp.zeros(x.shape[0], dtype=float, device="cpu")
        normal = wp.zeros(x.shape[0], dtype=wp.vec3, device="cpu")
        eval_sdf(geometry.shapes_struct("cpu"), points, distance, normal)
        d = distance.numpy()
        inside_wall = int(np.sum(d > 0.0))  # parcels meet the wall as points (kernels/reflect.py): d <= 0
        if inside_wall:
            errors.append(f"{inside_wall} parcel centres inside a wall (largest SDF {d.max():.3e} m)")
    removed = solver.pool.removed_count()
    injected = int(sum(entry["count"] for entry in solver.injected()))
    if int(alive.sum()) != injected - removed:
        errors.append(f"parcel count: {int(alive.sum())} alive != {injected} injected - {removed} removed")
    split, _ = holder_release(config)
    holder = [sum(s[side] for s in split) for side in (0, 1)]
    released = [0, 0]
    for k, entry in enumerate(solver.injected()):
        released[k // len(config.species())] += entry["count"]
    for side in (0, 1):
        if released[side] > holder[side]:
            errors.append(f"holder {side} released {released[side]} > {holder[side]} parcels")
    return errors


def summary(run) -> dict:
    """The rig's own keys of the summary (the report reads ``collisions``, ``dt``, ``diameter``, ``end_time``)."""
    config = run.args._rig
    collisions = run.series("collisions_collisions")
    overlaps = run.series("collisions_detected_pairs")
    return {"collisions": config.collisions, "diameter": config.diameter, "diameter2": config.diameter2,
            "mass_fraction2": config.mass_fraction2 if config.mixture else None,
            "particles_released": [n for _, _, n in config.species()],
            "particles_per_parcel_species": config.weights(),
            "real_particles_released": [n * w for (_, _, n), w in zip(config.species(), config.weights())],
            "ktgf_diameter": sauter_mean_of(config), "particles_per_parcel": config.particles_per_parcel,
            "particle_contacts": config.particle_contacts,
            "total_collisions": float(np.sum(collisions)) if collisions is not None else None,
            "total_overlap_pairs": int(np.sum(overlaps)) if overlaps is not None else 0,
            "collision_counts_available": hasattr(run.solver.collision, "counts")}


def report(run, summary: dict) -> str:
    config = run.args._rig
    sizes = (f"{config.diameter * 1e6:.0f}" if not config.mixture else
             f"{config.diameter * 1e6:.0f}/{config.diameter2 * 1e6:.0f} (mass fraction {config.mass_fraction2:g} of "
             f"the second; {config.particles} + {config.particles2} parcels of "
             f"{' + '.join(f'{w:g}' for w in config.weights())} particles)")
    total = summary.get("total_collisions")
    return (f"colliding_streams: {config.collisions}, d = {sizes} um, dt = {config.dt:g} s, {run.steps_this_call} "
            f"steps this call, t = {summary['simulated_time']:.4g} s on {int(np.prod(run.sim.grid.shape))} cells "
            f"({summary['fluid_cells']} fluid), {summary['injected']} parcels injected, {summary['removed']} removed, "
            f"{'-' if total is None else f'{total:g}'} collisions ({summary['total_overlap_pairs']} overlapping pairs "
            f"at step ends); step wall clock {summary['wall_clock_s']:.2f} s (loop with output "
            f"{summary['wall_clock_with_output_s']:.2f} s, Warp kernel loading {summary['kernel_load_s']:.2f} s, setup "
            f"+ gas warm-up {summary['setup_wall_clock_s']:.2f} s) -> {run.out}")


def options(groups) -> None:
    from hel_warp.errors import finite_float

    c, p, o = groups.case, groups.physics, groups.output
    c.add_argument("--diameter", type=finite_float, required=True, help="mean particle diameter, m (315e-6, 475e-6)")
    c.add_argument("--diameter2", type=finite_float, default=None,
                   help="a binary mixture: mean diameter of the second species, m (e.g. 475e-6; with "
                        "--mass-fraction2): both holders release both sizes")
    c.add_argument("--mass-fraction2", type=finite_float, default=None,
                   help="mass fraction of the --diameter2 species, in (0, 1) (e.g. 0.5)")
    c.add_argument("--cells", type=int, default=None, help="shrink the grid to about N cells (a reduced rig)")
    c.add_argument("--max-particles", type=int, default=None, help="cap the parcels released (a reduced rig)")
    c.add_argument("--real-particles", type=int, default=None,
                   help="one size: real particles released over the paper's window (default: the paper's parcels x "
                        "--particles-per-parcel, 12,000 x W at 315 um); parcels = real / W. The paper's second HEL "
                        "run: 96000 (its DEM reference: 96000 at weight 1)")
    c.add_argument("--monodisperse", action="store_true", help="all particles of the mean diameter")
    c.add_argument("--gas-warmup", type=finite_float, default=0.01, help="gas-only time before the release, s "
                                                                          "(default 0.01)")
    p.add_argument("--wall-contact", choices=("point", "surface"), default="surface",
                   help="where HEL parcels meet the walls: surface (a particle radius from the centre, as the dem's "
                        "spheres; default) or point (their centre, MP-PIC)")
    p.add_argument("--wall-spin", action="store_true",
                   help="HEL parcels meet the walls as rough spheres that carry their spin (a sphere rolling along a "
                        "wall keeps its speed), as the dem's spheres do; default: the spinless reflection with "
                        "Table 1's e_t = 0.8")
    p.add_argument("--no-particle-contacts", action="store_true",
                   help="dem only: no particle-particle contacts (walls, drag, injection as with contacts): the "
                        "walls-only reference")


def add_arguments(parser) -> None:
    """Every option of the case on ``parser`` (its own and the shared ones)."""
    CASE.add_arguments(parser)


def pooled_metrics(member_dirs, reference_dirs=None) -> dict:
    """The rig's figures pooled over an ensemble's members, for ``hel-warp ensemble`` (its table's ``pooled:`` rows):
    stream crossing and transverse v_y rms over the run, over sections 1-7 and per section, per size class, and the
    real collision rate, each against the ``--reference`` ensemble's with jackknife errors
    (``hel_warp.studies.rig_ensemble.case_hook``)."""
    from hel_warp.studies.rig_ensemble import case_hook

    return case_hook(member_dirs, reference_dirs)


CASE = hc.Case("colliding_streams", build, doc=__doc__, options=options, summary=summary,
               check=lambda run: check(run), report=report,
               defaults={"output_interval": 1.0e-3})


def main(argv=None) -> int:
    return CASE.main(argv)


if __name__ == "__main__":
    sys.exit(main())
