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

The step is engineer G's ``HelSolver.step`` (deposit, gas, interpolate, collide, push, outlets,
walls with e_n = e_t = 0.8, scheduled injection) driven by ``hel_warp.run.Run``, which writes
``OUT/run.zarr`` (particle snapshots with x, v, radius, weight, stream, particle_id; gas fields;
series ``timing_step``, ``timing_<sub-step>``, ``collisions_<kind>``), VTK files and checkpoints
(``--resume`` continues from the last one). The case adds attrs ``config.case`` (the settings, the
grid and the rig layout ``rig``: sections and axes, which ``hel-warp report`` reads) and, at the
end, ``summary`` (``collisions``, ``dt``, ``diameter``, ``end_time``, ``wall_clock_s`` = the sum of
the per-step wall clock, collision totals, ``check_errors``). ``check()`` verifies physical facts at
the end (no parcel centre inside a wall, parcels alive = injected - removed).

Further assumptions: gravity along +x (the rig upright, flow downwards, holders above the arms);
the gas runs alone for ``--gas-warmup`` (0.01 s) before the release ("once the flow is
stabilized", section 2); diameters normal with the paper's sigma (8.2 / 22 um), truncated at 3 sigma.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(REPO))

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


def build_geometry(dims: RigDimensions):
    """(Grid, Geometry, inlet speeds {patch: m/s}) of the rig; speeds make patch area x speed = the paper's flow."""
    from hel_warp.grid import Box, Channel, Geometry, Grid, Patch

    lo, hi = dims.domain()
    h = dims.spacing
    shape = tuple(max(1, int(math.ceil((b - a) / h - 1e-9))) for a, b in zip(lo, hi))
    grid = Grid(origin=lo, spacing=h, shape=shape)
    beyond = 5.0 * h  # shapes run past the inlet / outlet planes so that no wall sits on an open boundary
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
    big = 1.0
    regions = {
        "main_inlet": ((-big, -0.5 * dims.main_width, -big), (big, 0.5 * dims.main_width, big)),
        "left_inlet": ((-big, dims.side_offset - 0.5 * dims.side_width, -big),
                       (big, dims.side_offset + 0.5 * dims.side_width, big)),
        "right_inlet": ((-big, -dims.side_offset - 0.5 * dims.side_width, -big),
                        (big, -dims.side_offset + 0.5 * dims.side_width, big)),
    }
    flows = {"main_inlet": dims.main_flow, "left_inlet": dims.side_flow, "right_inlet": dims.side_flow}
    # discrete patch areas: fluid cells of the first layer whose centres lie in the patch region
    fluid = _fluid_mask(grid, Geometry(shapes=tuple(shapes)))
    centres = grid.cell_centres()[0]
    speeds = {}
    for name, (rlo, rhi) in regions.items():
        inside = ((centres[..., 1] >= rlo[1]) & (centres[..., 1] <= rhi[1]) & fluid[0])
        area = float(inside.sum()) * h * h
        if area == 0.0:
            from hel_warp.errors import ConfigError

            raise ConfigError(f"patch {name} covers no fluid cell at h = {h:.3g} m; use more --cells")
        speeds[name] = flows[name] / area
    patches = [Patch(name=name, kind="inlet", axis=0, side="min", lo=rlo, hi=rhi, velocity=(speeds[name], 0.0, 0.0))
               for name, (rlo, rhi) in regions.items()]
    patches.append(Patch(name="outlet", kind="outlet", axis=0, side="max", pressure=0.0))
    return grid, Geometry(shapes=tuple(shapes), patches=tuple(patches)), speeds


def _fluid_mask(grid, geometry) -> np.ndarray:
    import warp as wp

    from kernels import sdf as sdf_kernels

    cell_fluid = wp.zeros(grid.shape, dtype=wp.int32, device="cpu")
    sdf_kernels.eval_fluid_mask(geometry.shapes_struct("cpu"), grid.origin, grid.spacing, cell_fluid)
    return cell_fluid.numpy().astype(bool)


# ---------------------------------------------------------------------------------------------- the case
@dataclass(frozen=True, kw_only=True)
class CaseConfig:
    """One run of the rig (validated by :func:`make_config`)."""

    diameter: float
    """Mean particle diameter, m (paper: 315e-6 or 475e-6)."""
    dt: float
    """HEL time step, s (paper: 1e-3, 1e-4, 7.14e-5)."""
    collisions: str
    """Collision model: none, ktgf, surrogate, surrogate-paper, dem."""
    end_time: float
    """Simulated time after the particle release, s (paper: 0.02-0.03)."""
    particle_contacts: bool = True
    """``dem`` only: False switches the particle-particle contacts off (walls, drag, injection unchanged): the
    like-with-like run that, beside ``none``, shows how much of a gap the walls alone make (issue 11)."""
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
    output_interval: float = 1.0e-3
    """Simulated time between particle snapshots, s (the report averages over snapshots)."""
    model: str | None = None
    """Surrogate model directory (surrogate and surrogate-paper)."""
    detection: str = "swept"
    """``surrogate`` pair detection: ``swept`` (continuous, default), ``overlap`` (the paper's end-of-step test) or
    ``cell`` (stochastic per grid cell, the default with ``particles_per_parcel`` > 1; hel_warp/cell_collisions.py)."""
    wall_contact: str = "surface"
    """Where HEL parcels meet the walls: ``surface`` (default: a particle radius from the centre, as the ``dem``
    spheres, so that HEL and its reference share the walls' geometry) or ``point`` (their centre, MP-PIC;
    ``HelConfig.wall_contact``). ``dem`` keeps its Hertz-Mindlin wall contact."""
    wall_spin: bool = False
    """HEL parcels meet the walls as rough spheres that carry their spin (``HelConfig.wall_spin``), as the ``dem``
    spheres roll; False: the spinless reflection with Table 1's e_t = 0.8."""
    particle_spin: bool = False
    """``surrogate`` (pairwise): collisions at the contact point, the spins turned (``HelConfig.particle_spin``)."""
    parcel_cloud: str = "density"
    """How wide weighted parcels couple to the gas (``HelConfig.parcel_cloud``)."""
    cell_coarsen: int | None = None
    """``surrogate`` cell detection: grid cells per collision cell and axis (``CellConfig.coarsen``; None: the
    automatic choice, merged cells for weighted parcels)."""
    cell_packing_stress: bool = True
    """``surrogate`` cell detection: the MP-PIC packing stress (``CellConfig.packing_stress``)."""
    cell_nearest: int = 0
    """``surrogate`` cell detection: nearest-neighbour partners among this many parcels (``CellConfig.nearest``;
    0: random partners)."""
    cell_subdivision: int = 1
    """``surrogate`` cell detection: sub-cells per grid cell and axis (``CellConfig.subdivision``; 1: the grid cell
    at weight 1, merged cells above it)."""
    cell_cfl: float = 1.0
    """``surrogate`` cell detection: largest path of a parcel per collision sub-step, in cell edges
    (``CellConfig.cfl``)."""
    cell_approaching: bool | None = None
    """``surrogate`` cell detection: only pairs whose centres approach collide (``CellConfig.approaching``);
    None: the ``CellConfig`` default (on when a parcel weighs more than 1, off at weight 1; FIGURES, issue 12,
    twenty-eighth session)."""
    cell_transfer: bool | None = None
    """``surrogate`` cell detection: the collisional transfer, colliders moved apart by their share of the contact
    distance (``CellConfig.collisional_transfer``); None: the ``CellConfig`` default."""
    cell_local_density: bool | None = None
    """``surrogate`` cell detection: in merged cells a pair's rate takes the deposited solids fraction around its
    parcels (``CellConfig.local_density``); None: the ``CellConfig`` default."""
    wall_events: bool = True
    """``surrogate`` swept detection: walls as events within the step, in time order with the collisions (False:
    the push's end-of-step reflection; ``SurrogateCollision.wall_events``)."""
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
    from hel_warp.errors import ConfigError

    if not args.diameter > 0:
        raise ConfigError(f"--diameter must be > 0 m (got {args.diameter}); e.g. 315e-6")
    if not args.dt > 0:
        raise ConfigError(f"--dt must be > 0 s (got {args.dt})")
    if not args.end_time > 0:
        raise ConfigError(f"--end-time must be > 0 s (got {args.end_time})")
    if args.end_time < args.dt * (1.0 - 1e-9):
        raise ConfigError(f"--end-time {args.end_time:g} s is shorter than one step (--dt {args.dt:g} s), so the "
                          "run would take no step; give an end time of at least one step")
    from hel_warp.run import check_device

    check_device(args.device)
    from hel_warp.mixture import species_weights

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
    if getattr(args, "collision_events", None) and args.collisions in ("none", "ktgf"):
        raise ConfigError(f"--collision-events records the dem and surrogate collisions; --collisions "
                          f"{args.collisions} resolves none")
    if getattr(args, "particle_spin", False) and args.collisions != "surrogate":
        raise ConfigError(f"--particle-spin turns the surrogate's collisions at the contact point; --collisions "
                          f"{args.collisions} does not use it (the dem's spheres spin on their own)")
    if (args.collisions.startswith("surrogate")) and not args.model:
        raise ConfigError(f"--collisions {args.collisions} needs --model MODEL_DIR (a `hel-warp train` output)")
    detection = getattr(args, "detection", None)
    coarsen = getattr(args, "cell_coarsen", None)
    uses_cell = args.collisions == "surrogate" and (detection == "cell" or (detection is None and max(weights) > 1))
    nearest = getattr(args, "cell_nearest", None)
    subdivision = getattr(args, "cell_subdivision", None)
    cfl = getattr(args, "cell_cfl", None)
    for flag, given in (("--cell-coarsen", coarsen is not None), ("--cell-nearest", nearest is not None),
                        ("--cell-subdivision", subdivision is not None), ("--cell-cfl", cfl is not None),
                        ("--no-packing-stress", getattr(args, "no_packing_stress", False)),
                        ("--[no-]cell-approaching", getattr(args, "cell_approaching", None) is not None),
                        ("--[no-]cell-transfer", getattr(args, "cell_transfer", None) is not None),
                        ("--[no-]cell-local-density", getattr(args, "cell_local_density", None) is not None)):
        if given and not uses_cell:
            raise ConfigError(f"{flag} is an option of the surrogate's cell detection (give --detection cell or "
                              "--particles-per-parcel > 1)")
    if nearest is not None and nearest < 0:
        raise ConfigError(f"--cell-nearest must be >= 0 parcels (got {nearest}; 0: random partners)")
    if coarsen is not None and coarsen < 1:
        raise ConfigError(f"--cell-coarsen must be >= 1 grid cell (got {coarsen})")
    if subdivision is not None and subdivision < 1:
        raise ConfigError(f"--cell-subdivision must be >= 1 sub-cell per grid cell and axis (got {subdivision})")
    if subdivision is not None and subdivision > 1 and coarsen is not None and coarsen > 1:
        raise ConfigError("--cell-subdivision and --cell-coarsen exclude each other: give one of them")
    if cfl is not None and not (math.isfinite(cfl) and cfl > 0.0):
        raise ConfigError(f"--cell-cfl must be > 0 cell edges per sub-step (got {cfl})")
    if getattr(args, "no_wall_events", False) and (args.collisions != "surrogate" or detection in ("overlap", "cell")):
        raise ConfigError("--no-wall-events is an option of the surrogate's swept detection (got --collisions "
                          f"{args.collisions}{' --detection ' + detection if detection else ''})")
    if detection is not None and args.collisions != "surrogate":
        raise ConfigError(f"--detection is a surrogate option (got --collisions {args.collisions}); surrogate-paper "
                          "keeps the paper's overlap test")
    mixture = mixture_release(args, args.diameter, std, known if paper_size else None, weights)
    if mixture is not None:
        particles = mixture.pop("particles")
        mass_flow = mixture.pop("mass_flow")
    else:
        mass_flow = PAPER_MASS_FLOW[known] if paper_size else DEFAULT_MASS_FLOW
        mixture = {}
    return CaseConfig(diameter=float(args.diameter), dt=float(args.dt), collisions=args.collisions,
                      end_time=float(args.end_time), particles_per_parcel=float(weights[0]),
                      particle_contacts=not args.no_particle_contacts,
                      particles=particles, diameter_std=std, **mixture, release_weight=release_weight,
                      mass_flow=mass_flow, cells=args.cells,
                      gas_warmup=float(args.gas_warmup), output_interval=float(args.output_interval),
                      model=args.model, detection=detection or ("cell" if max(weights) > 1 else "swept"),
                      wall_events=not getattr(args, "no_wall_events", False), cell_coarsen=coarsen,
                      cell_packing_stress=not getattr(args, "no_packing_stress", False),
                      cell_nearest=int(nearest or 0), cell_approaching=getattr(args, "cell_approaching", None),
                      cell_transfer=getattr(args, "cell_transfer", None),
                      cell_local_density=getattr(args, "cell_local_density", None),
                      cell_subdivision=int(subdivision or 1), cell_cfl=float(cfl if cfl is not None else 1.0),
                      wall_contact=getattr(args, "wall_contact", "surface"),
                      wall_spin=bool(getattr(args, "wall_spin", False)),
                      particle_spin=bool(getattr(args, "particle_spin", False)),
                      parcel_cloud=getattr(args, "parcel_cloud", "density"),
                      seed=int(args.seed), device=args.device)


def sauter_mean_of(config: CaseConfig) -> float:
    """The one diameter KTGF gets: the mean diameter, or a mixture's Sauter mean d_32 = sum N E[d^3] / sum N E[d^2]
    (the mixture KTGF closures are out of scope)."""
    from hel_warp.mixture import sauter_mean

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

    from hel_warp.mixture import second_size

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


def check_model(model_dir: str, diameter: float, density: float, force: bool, diameters=None,
                force_flag: str = "--force") -> dict:
    """Refuse a surrogate trained for another particle size or material (metadata ``defaults``: mean d1, rho1).

    Sizes within 10 % (the paper's size distributions are +-3 sigma = +-8 % at 315 um) and densities within
    1 % pass; anything else, or a model whose metadata does not say, needs ``--force``. A mixture
    (``diameters``) needs a model whose training domain holds every size and size ratio
    (``hel_warp.mixture.model_domain_problem``) instead of the 10 % rule. Returns the metadata. ``force_flag``: the
    option the error names (the caller's).
    """
    from hel_warp.errors import ConfigError

    path = os.path.join(model_dir, "metadata.json")
    try:
        with open(path) as fh:
            meta = json.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"{path} not found; --model must be a directory written by `hel-warp train`") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path} is not valid JSON ({exc})") from None
    defaults = meta.get("defaults") if isinstance(meta, dict) else None
    problems = []
    if not isinstance(defaults, dict) or "d1" not in defaults or "rho1" not in defaults:
        problems.append("its metadata does not record the particle size and density it was trained for")
    else:
        d_model, rho_model = float(defaults["d1"]), float(defaults["rho1"])
        if diameters is not None:
            from hel_warp.mixture import model_domain_problem

            problem = model_domain_problem(meta, diameters)
            if problem:
                problems.append(problem)
        elif abs(d_model - diameter) > 0.10 * diameter:
            problems.append(f"it was trained for d = {d_model * 1e6:.0f} um, the run has {diameter * 1e6:.0f} um")
        if abs(rho_model - density) > 0.01 * density:
            problems.append(f"it was trained for density {rho_model:g} kg/m^3, the run has {density:g} kg/m^3")
    if problems and not force:
        raise ConfigError(f"model {model_dir}: {'; '.join(problems)}; train a model for this particle or pass "
                          f"{force_flag} to use it anyway")
    return meta


class CollidingStreams:
    """The rig: gas solver, parcel pool and ``HelSolver`` (walls, two scheduled injectors, two outlet planes).

    ``step()`` is one HEL step (deposit, gas, interpolate, collide, push, outlets, walls, inject; engineer
    G's ``HelSolver.step``); ``snapshot()`` the output hook; :func:`check` the physical facts.
    """

    def __init__(self, config: CaseConfig):
        from hel_warp._warp import init_warp
        from hel_warp.coupling import PushConfig
        from hel_warp.gas import GasConfig, GasField, GasSolver
        from hel_warp.hel import HelConfig, HelSolver, Outlet, ScheduledInjection, collision_model
        from hel_warp.material import Material
        from hel_warp.parcels import ParcelPool, VolumeInjection

        init_warp()
        self.config = config
        self.dims = dimensions_for_cells(config.cells)
        self.grid, self.geometry, self.inlet_speeds = build_geometry(self.dims)
        device = config.device
        self.domain = self.geometry.build(self.grid, device=device)
        gas_config = GasConfig()
        self.gas_solver = GasSolver(self.domain, gas_config, device=device)
        self.gas = GasField(self.domain, device=device)
        self.pool = ParcelPool.empty(sum(n for _, _, n in config.species()), device=device)
        material = Material(density=config.density)
        push = PushConfig(fluid_density=gas_config.density, fluid_viscosity=gas_config.viscosity,
                          gravity=config.gravity)
        kwargs = {}
        self.ktgf_diameter = sauter_mean_of(config)
        if config.collisions == "ktgf":  # one diameter: a mixture's Sauter mean (no mixture KTGF closures)
            kwargs = {"particle_diameter": self.ktgf_diameter, "particle_density": config.density}
        elif config.collisions == "surrogate":
            kwargs = {"model_dir": config.model, "detection": config.detection, "seed": config.seed,
                      "wall_events": config.wall_events}
            if (config.cell_coarsen is not None or not config.cell_packing_stress or config.cell_nearest
                    or config.cell_approaching is not None or config.cell_subdivision != 1 or config.cell_cfl != 1.0
                    or config.cell_transfer is not None or config.cell_local_density is not None):
                from hel_warp.cell_collisions import CellConfig

                optional = {} if config.cell_approaching is None else {"approaching": config.cell_approaching}
                if config.cell_local_density is not None:
                    optional["local_density"] = config.cell_local_density
                kwargs["cell"] = CellConfig(coarsen=config.cell_coarsen, packing_stress=config.cell_packing_stress,
                                            nearest=config.cell_nearest, subdivision=config.cell_subdivision,
                                            cfl=config.cell_cfl, collisional_transfer=config.cell_transfer,
                                            **optional)
        elif config.collisions == "surrogate-paper":
            kwargs = {"model_dir": config.model}
        elif config.collisions == "dem":
            kwargs = {"material": material}
            if not config.particle_contacts:
                kwargs["particle_contacts"] = _dem_particle_contacts_option(False)
        self.collision = collision_model(config.collisions, **kwargs)
        # each holder releases half of the parcels at its measured mass flow (section 2): a window of
        # (parcels x particle mass) / mass flow, for one size the same for any particles-per-parcel (the parcel
        # count stays); a mixture: every holder releases half of each species, all species over the holder's one
        # window of its real mass (parcels x weight x particle mass) / mass flow
        species = config.species()
        weights = config.weights()
        mass_weights = config.release_weights()
        self.particle_mass = config.density * math.pi / 6.0 * (config.diameter**3
                                                                + 3.0 * config.diameter * config.diameter_std**2)
        split = [(n // 2, n - n // 2) for _, _, n in species]  # per species: (left, right) parcels
        self.holder_parcels = tuple(sum(s[side] for s in split) for side in (0, 1))
        margin = max(0.5 * d + 1.5 * sd for d, sd, _ in species)
        injectors = []
        self.release_window = []
        self.injector_side = []  # the holder of each injector
        for side in (0, 1):
            lo, hi = self.dims.injection_box(side, margin)
            holder_mass = sum(split[k][side] * mass_weights[k] * config.density * math.pi / 6.0
                              * (d**3 + 3.0 * d * sd**2) for k, (d, sd, _) in enumerate(species))
            window = holder_mass / config.mass_flow[side]
            self.release_window.append(window)
            for k, (d, sd, _) in enumerate(species):
                self.injector_side.append(side)
                injectors.append(ScheduledInjection(
                    injection=VolumeInjection(box_lo=lo, box_hi=hi, diameter_mean=d, diameter_std=sd,
                                              density=config.density, count=split[k][side],
                                              speed=self.dims.injection_speed, direction=(1.0, 0.0, 0.0),
                                              weight=weights[k], stream=side,
                                              seed=config.seed + 1000 * k),
                    t_start=0.0, t_end=window))
        outlets = (Outlet(point=(self.dims.main_length, 0.0, 0.0), normal=(1.0, 0.0, 0.0)),
                   Outlet(point=(0.0, 0.0, 0.0), normal=(-1.0, 0.0, 0.0)))  # back out through an inlet plane
        self.solver = HelSolver(pool=self.pool, gas_solver=self.gas_solver, gas=self.gas,
                                config=HelConfig(dt=config.dt, push=push, material=material, walls=True,
                                                 wall_contact=config.wall_contact, wall_spin=config.wall_spin,
                                                 particle_spin=config.particle_spin, injectors=tuple(injectors),
                                                 outlets=outlets, parcel_cloud=config.parcel_cloud),
                                collision=self.collision)

    @property
    def fluid_cells(self) -> int:
        return int(self.domain.cell_fluid.numpy().sum())

    @property
    def injected(self) -> int:
        return int(sum(entry["count"] for entry in self.solver.injected()))

    def warm_up(self) -> int:
        """Gas-only steps of at most 1e-3 s over ``gas_warmup`` s (the flow is established before the release)."""
        if self.config.gas_warmup <= 0:
            return 0
        n = int(math.ceil(self.config.gas_warmup / 1e-3 - 1e-9))
        for _ in range(n):
            self.gas_solver.step(self.gas, self.config.gas_warmup / n)
        return n

    def step(self) -> dict:
        """One HEL step; returns this step's collision counts."""
        self.solver.step()
        return self.solver.collision_counts()

    def snapshot(self) -> dict:
        """Host arrays of the live parcels (output intervals only)."""
        p = self.pool.particles
        alive = p.alive.numpy().astype(bool)
        return {name: getattr(p, name).numpy()[alive]
                for name in ("x", "v", "radius", "weight", "density", "stream", "particle_id")}

    def rig_layout(self) -> dict:
        """What the report needs to know about the rig (stored in the run's attrs)."""
        lo, hi = self.dims.domain()
        return {"axial_axis": 0, "transverse_axis": 1, "depth_axis": 2, "downstream": [1.0, 0.0, 0.0],
                "sections": self.dims.sections(), "domain_lo": list(lo), "domain_hi": list(hi),
                "main_width": self.dims.main_width, "main_depth": self.dims.main_depth,
                "streams": {"0": "left", "1": "right"}, "axis_transverse": 0.0,
                "stream_sides": {"0": 1.0, "1": -1.0},  # sign of y - axis on each stream's own arm (left = +y)
                "dimensions": asdict(self.dims),
                "size_classes": [{"diameter": d, "diameter_std": sd, "parcels": n, "particles_per_parcel": w}
                                 for (d, sd, n), w in zip(self.config.species(), self.config.weights())]
                if self.config.mixture else None}


def _dem_particle_contacts_option(value: bool) -> bool:
    """``value`` if ``DemCollision`` takes ``particle_contacts``, else a ConfigError (an engine without it)."""
    import inspect

    from hel_warp.hel import COLLISION_MODELS
    from hel_warp.errors import ConfigError

    if "particle_contacts" not in inspect.signature(COLLISION_MODELS["dem"].__init__).parameters:
        raise ConfigError("--no-particle-contacts: this engine's DemCollision has no particle_contacts option yet; "
                          "run dem with contacts")
    return value


def check(rig: CollidingStreams) -> list[str]:
    """Physical facts at the end of the run; the list of violations (empty = pass).

    - no live parcel centre lies in a wall (SDF > 0; MP-PIC parcels meet the wall as points, so a centre may
      sit on it) and every position / velocity is finite;
    - parcels alive = parcels injected - parcels removed at the outlets;
    - every holder released no more than its share.
    """
    import warp as wp

    from kernels.sdf import eval_sdf

    errors = []
    p = rig.pool.particles
    alive = p.alive.numpy().astype(bool)
    x = p.x.numpy()[alive]
    v = p.v.numpy()[alive]
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v))):
        errors.append("non-finite parcel positions or velocities")
    if x.shape[0]:
        points = wp.array(x, dtype=wp.vec3, device="cpu")
        distance = wp.zeros(x.shape[0], dtype=float, device="cpu")
        normal = wp.zeros(x.shape[0], dtype=wp.vec3, device="cpu")
        eval_sdf(rig.geometry.shapes_struct("cpu"), points, distance, normal)
        d = distance.numpy()
        inside_wall = int(np.sum(d > 0.0))  # parcels meet the wall as points (kernels/reflect.py): d <= 0
        if inside_wall:
            errors.append(f"{inside_wall} parcel centres inside a wall (largest SDF {d.max():.3e} m)")
    removed = rig.pool.removed_count()
    if int(alive.sum()) != rig.injected - removed:
        errors.append(f"parcel count: {int(alive.sum())} alive != {rig.injected} injected - {removed} removed")
    released = [0, 0]
    for side, entry in zip(rig.injector_side, rig.solver.injected()):
        released[side] += entry["count"]
    for side in (0, 1):
        if released[side] > rig.holder_parcels[side]:
            errors.append(f"holder {side} released {released[side]} > {rig.holder_parcels[side]} parcels")
    return errors


# ---------------------------------------------------------------------------------------------- running
def prepare_out(out: str, overwrite: bool, resume: bool) -> str:
    """'new' or 'resume-complete'; refuses an existing run directory without --overwrite / --resume."""
    from hel_warp.errors import ConfigError

    path = Path(out)
    if overwrite and resume:
        raise ConfigError("give at most one of --overwrite and --resume")
    if not path.exists():
        if resume:
            raise ConfigError(f"--resume: run directory {out} does not exist")
        return "new"
    if resume:
        return "resume"
    if not overwrite:
        raise ConfigError(f"run directory {out} exists; pass --overwrite to replace it or --resume to continue it")
    if path.is_dir() and any(path.iterdir()) and not (path / "run.zarr").exists():
        raise ConfigError(f"{out} is not a run directory (no run.zarr); --overwrite only replaces run directories")
    shutil.rmtree(path) if path.is_dir() else path.unlink()
    return "new"


def _jsonable(value):
    from hel_warp.io import _jsonable as jsonable

    return jsonable(value)


def case_attrs(rig: CollidingStreams, config: CaseConfig) -> dict:
    """The case settings stored in the run's attrs (``config.case``); a --resume must match them, so the
    end time and output settings (which a resume may change) are not among them."""
    settings = {k: v for k, v in asdict(config).items() if k not in ("end_time", "output_interval")}
    return _jsonable({"case": "colliding_streams", **settings,
                      "grid_shape": list(rig.grid.shape), "grid_cells": int(np.prod(rig.grid.shape)),
                      "fluid_cells": rig.fluid_cells, "spacing": rig.grid.spacing, "inlet_speeds": rig.inlet_speeds,
                      "inlet_flows_l_per_min": {"main": rig.dims.main_flow / LITRE_PER_MIN,
                                                "side": rig.dims.side_flow / LITRE_PER_MIN},
                      "release_window_s": rig.release_window, "rig": rig.rig_layout(),
                      "collision_counts_available": hasattr(rig.collision, "counts")})


class EventRecorder:
    """``--collision-events PATH``: every collision of every step of this call, for ``scripts/collision_events.py``:
    ``dem`` contact onsets (``DemCollision.onset_events``), the ``surrogate``'s resolved collisions with swept or
    overlap detection (``SurrogateCollision.collision_events``; switched on here). Saved as one ``.npz`` of equal-length
    arrays: ``step``, ``particle_a`` < ``particle_b`` (ids), ``speed`` (normal approach speed, m/s), ``time`` (s of
    the run), ``stream_a`` <= ``stream_b``, ``radius_a``, ``radius_b`` (m), and ``truncated_steps`` (steps whose list
    overflowed; their counts in the run's series stay exact)."""

    def __init__(self, rig: "CollidingStreams"):
        from hel_warp.errors import ConfigError

        collision = rig.collision
        if hasattr(collision, "record_events"):
            collision.record_events = True
            self._read = collision.collision_events
        elif hasattr(collision, "onset_events"):
            self._read = collision.onset_events
        else:
            raise ConfigError(f"--collision-events records the dem and surrogate collisions (got --collisions "
                              f"{rig.config.collisions}, which resolves none)")
        self.rows = {k: [] for k in ("step", "particle_a", "particle_b", "speed", "time", "stream_a", "stream_b",
                                     "radius_a", "radius_b")}
        self.truncated = []

    def add(self, solver) -> None:
        ev = self._read()
        n = len(ev["speed"])
        p = solver.pool.particles
        radius = np.full(max(int(p.particle_id.numpy().max(initial=0)) + 1, 1), np.nan, np.float32)
        alive = p.alive.numpy() != 0
        radius[p.particle_id.numpy()[alive]] = p.radius.numpy()[alive]
        step = solver.step_count - 1
        r = self.rows
        r["step"].append(np.full(n, step, np.int32))
        for key in ("particle_a", "particle_b", "speed", "stream_a", "stream_b"):
            r[key].append(np.asarray(ev[key]))
        r["time"].append(np.asarray(ev["time"], np.float64) + (solver.time - solver.config.dt))
        r["radius_a"].append(radius[np.asarray(ev["particle_a"], np.int64)])
        r["radius_b"].append(radius[np.asarray(ev["particle_b"], np.int64)])
        if ev.get("truncated"):
            self.truncated.append(step)

    def save(self, path: str) -> None:
        out = {k: (np.concatenate(v) if v else np.zeros(0)) for k, v in self.rows.items()}
        np.savez_compressed(path, **out, truncated_steps=np.asarray(self.truncated, np.int32))


def run(args, *, progress: bool = True) -> int:
    """Build the rig, warm the gas up, step to --end-time with ``hel_warp.run.Run`` (checkpoints, --resume)."""
    import zarr

    from hel_warp.run import Run, RunConfig, load_kernels

    config = make_config(args)
    mode = prepare_out(args.out, args.overwrite, args.resume)
    model_meta = None
    if config.collisions.startswith("surrogate"):
        model_meta = check_model(config.model, config.diameter, config.density, args.force,
                                 diameters=[d for d, _, _ in config.species()] if config.mixture else None)
    kernel_load_s = load_kernels(config.device)  # compile before anything is timed (the rig build launches kernels)
    t_setup = time.perf_counter()
    rig = CollidingStreams(config)
    warm_steps = 0 if mode == "resume" else rig.warm_up()  # a resume restores the gas from the checkpoint
    setup_s = time.perf_counter() - t_setup
    if mode == "resume" and not (Path(args.out) / "checkpoint.npz").exists() \
            and not (Path(args.out) / "checkpoint.prev.npz").exists():
        from hel_warp.errors import ConfigError

        raise ConfigError(f"--resume: {args.out} holds no checkpoint; rerun with --overwrite")
    runner = Run(rig.solver, RunConfig(out_dir=args.out, end_time=config.end_time,
                                       output_interval=config.output_interval, vtk=not args.no_vtk,
                                       gas_snapshots=not args.no_gas_snapshots),
                 case_config=case_attrs(rig, config), restart=mode == "resume")
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=runner.total_steps, initial=rig.solver.step_count, unit="step",
                   desc=f"colliding_streams {config.collisions} dt={config.dt:g}")
    events = EventRecorder(rig) if getattr(args, "collision_events", None) else None

    def callback(solver):
        if events is not None:
            events.add(solver)
        if bar is not None:
            bar.update(1)
    t_loop = time.perf_counter()
    taken = runner.run(progress=callback)
    loop_total_s = time.perf_counter() - t_loop
    if bar is not None:
        bar.close()
    if events is not None:
        events.save(args.collision_events)
    errors = check(rig)
    root = zarr.open_group(str(Path(args.out) / "run.zarr"), mode="r+")
    root.attrs["kernel_load_s"] = float(root.attrs.get("kernel_load_s", 0.0)) + kernel_load_s
    series = root["series"]
    step_wall = np.asarray(series["timing_step"][...], np.float64) if "timing_step" in series else np.zeros(0)
    # real binary collisions (counts() "collisions": dem contact onsets, surrogate resolved collisions weighted by
    # min(w_i, w_j)) and the pairs overlapping at step ends ("detected_pairs"); per stream pair in their own series
    collisions = float(np.sum(series["collisions_collisions"][...])) if "collisions_collisions" in series else None
    overlaps = int(np.sum(series["collisions_detected_pairs"][...])) if "collisions_detected_pairs" in series else 0
    summary = {"collisions": config.collisions, "dt": config.dt, "diameter": config.diameter,
               "diameter2": config.diameter2, "mass_fraction2": config.mass_fraction2 if config.mixture else None,
               "particles_released": [n for _, _, n in config.species()],
               "particles_per_parcel_species": config.weights(),
               "real_particles_released": [n * w for (_, _, n), w in zip(config.species(), config.weights())],
               "ktgf_diameter": rig.ktgf_diameter,
               "end_time": config.end_time, "simulated_time": rig.solver.time, "steps": rig.solver.step_count,
               "status": "complete" if rig.solver.step_count >= runner.total_steps else "running",
               "wall_clock_s": float(step_wall.sum()),
               "wall_clock_with_output_s": (root.attrs.get("summary", {}).get("wall_clock_with_output_s", 0.0)
                                            if mode == "resume" else 0.0) + loop_total_s,
               "setup_wall_clock_s": setup_s, "warmup_steps": warm_steps,
               "particles_per_parcel": config.particles_per_parcel,
               "kernel_load_s": float(root.attrs.get("kernel_load_s", 0.0)),
               "particle_contacts": config.particle_contacts,
               "injected": rig.injected, "removed": rig.pool.removed_count(), "total_collisions": collisions,
               "total_overlap_pairs": overlaps,
               "collision_counts_available": hasattr(rig.collision, "counts"),
               "model_metadata": ({k: model_meta.get(k) for k in ("form", "dataset_hash", "defaults")}
                                  if model_meta else None),
               "check_errors": errors}
    root.attrs["summary"] = _jsonable(summary)
    sizes = (f"{config.diameter * 1e6:.0f}" if not config.mixture else
             f"{config.diameter * 1e6:.0f}/{config.diameter2 * 1e6:.0f} (mass fraction {config.mass_fraction2:g} of "
             f"the second; {config.particles} + {config.particles2} parcels of "
             f"{' + '.join(f'{w:g}' for w in config.weights())} particles)")
    print(f"colliding_streams: {config.collisions}, d = {sizes} um, dt = {config.dt:g} s, "
          f"{taken} steps this call, t = {rig.solver.time:.4g} s on {int(np.prod(rig.grid.shape))} cells "
          f"({rig.fluid_cells} fluid), {rig.injected} parcels injected, {rig.pool.removed_count()} removed, "
          f"{'-' if collisions is None else f'{collisions:g}'} collisions ({overlaps} overlapping pairs at step "
          f"ends); step wall clock {summary['wall_clock_s']:.2f} s (loop with output "
          f"{loop_total_s:.2f} s, Warp kernel loading {summary['kernel_load_s']:.2f} s, setup + gas warm-up "
          f"{setup_s:.2f} s) -> {args.out}")
    for e in errors:
        print(f"check failed: {e}", file=sys.stderr)
    return 1 if errors else 0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from hel_warp.errors import finite_float

    parser.add_argument("--diameter", type=finite_float, required=True,
                        help="mean particle diameter, m (315e-6, 475e-6)")
    parser.add_argument("--diameter2", type=finite_float, default=None,
                        help="a binary mixture: mean diameter of the second species, m (e.g. 475e-6; with "
                             "--mass-fraction2): both holders release both sizes")
    parser.add_argument("--mass-fraction2", type=finite_float, default=None,
                        help="mass fraction of the --diameter2 species, in (0, 1) (e.g. 0.5)")
    parser.add_argument("--dt", type=finite_float, required=True, help="HEL time step, s (1e-3, 1e-4, 7.14e-5)")
    parser.add_argument("--collisions", choices=COLLISIONS, required=True, help="collision model")
    parser.add_argument("--end-time", type=finite_float, required=True, help="simulated time after release, s")
    parser.add_argument("--out", required=True, help="run directory (refused if it exists, see --overwrite/--resume)")
    parser.add_argument("--model", default=None, help="surrogate model directory (hel-warp train output)")
    parser.add_argument("--detection", choices=("swept", "overlap", "cell"), default=None,
                        help="surrogate pair detection: swept (continuous, default), overlap (the paper's "
                             "end-of-step test) or cell (stochastic per grid cell; default with "
                             "--particles-per-parcel > 1)")
    parser.add_argument("--wall-contact", choices=("point", "surface"), default="surface",
                        help="where HEL parcels meet the walls: surface (a particle radius from the centre, as the "
                             "dem's spheres; default) or point (their centre, MP-PIC)")
    parser.add_argument("--wall-spin", action="store_true",
                        help="HEL parcels meet the walls as rough spheres that carry their spin (Walton's law, "
                             "beta = 0: a sphere rolling along a wall keeps its speed), as the dem's spheres do; "
                             "default: the spinless reflection with Table 1's e_t = 0.8")
    parser.add_argument("--particle-spin", action="store_true",
                        help="surrogate: particle-particle collisions at the contact point, the spins turned (with "
                             "--wall-spin the parcels carry the spin they get rolling on the walls into their "
                             "collisions, as the dem's spheres do)")
    parser.add_argument("--collision-events", metavar="PATH", default=None,
                        help="save every collision of every step to PATH (.npz: ids, normal approach speed, time, "
                             "stream tags, radii; dem contact onsets or the surrogate's resolved collisions) for "
                             "scripts/collision_events.py")
    parser.add_argument("--no-wall-events", action="store_true",
                        help="surrogate swept detection: walls only at the step's end (the push's reflection) "
                             "instead of as events in time order with the collisions (the default)")
    parser.add_argument("--force", action="store_true",
                        help="use a model trained for another particle size or material (refused otherwise)")
    parser.add_argument("--no-particle-contacts", action="store_true",
                        help="dem only: no particle-particle contacts (walls, drag, injection as with contacts)")
    parser.add_argument("--particles-per-parcel", default="1",
                        help="real particles per parcel (paper's second HEL run: 8); default 1. A mixture: W for "
                             "both species or W1,W2 per species (the real mass stays, parcels = real / W_k)")
    parser.add_argument("--device", default="cpu", help="Warp device: cpu or cuda (default cpu)")
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--overwrite", action="store_true", help="replace an existing run directory")
    group.add_argument("--resume", action="store_true", help="continue an existing run directory")
    parser.add_argument("--cells", type=int, default=None, help="shrink the grid to about N cells (CI)")
    parser.add_argument("--cell-coarsen", type=int, default=None,
                        help="cell detection: grid cells per collision cell and axis (default: 1 at weight 1, else "
                             "the smallest that keeps a parcel pair from saturating, 4 on the 1 mm grid at 8 per "
                             "parcel)")
    parser.add_argument("--cell-nearest", type=int, default=None,
                        help="cell detection: the partner of a candidate is the nearest of up to N parcels of its "
                             "cell (Bird's nearest-neighbour collisions; default 0: a random one)")
    parser.add_argument("--cell-subdivision", type=int, default=None,
                        help="cell detection: sub-cells per grid cell and axis (default 1; finer cells sample "
                             "pairs closer together, at more cost, and warn when a pair saturates)")
    parser.add_argument("--cell-cfl", type=finite_float, default=None,
                        help="cell detection: largest path of a parcel per collision sub-step, in cell edges "
                             "(default 1)")
    parser.add_argument("--cell-approaching", action=argparse.BooleanOptionalAction, default=None,
                        help="cell detection: only parcel pairs whose centres approach collide, a receding pair "
                             "handing its collision to an approaching one of its cell, so that a cell collides as "
                             "often as Bird's NTC says while two streams that have passed each other in it stop "
                             "colliding (default: on when a parcel weighs more than 1, off at weight 1; "
                             "--no-cell-approaching: plain NTC, any pair of the cell, which crosses ~0.05 too much "
                             "at 64 particles per parcel; FIGURES, issue 12, twenty-eighth and twenty-ninth "
                             "sessions)")
    parser.add_argument("--cell-transfer", action=argparse.BooleanOptionalAction, default=None,
                        help="cell detection: the collisional transfer of the consistent Boltzmann algorithm, the "
                             "two parcels of each collision moved apart by their share of the contact distance, so "
                             "that a dense cloud pushes back as the DEM's spheres do (default: on; "
                             "--no-cell-transfer: plain NTC, whose crossing is further from "
                             "the CFD-DEM at every weight and transverse spread 1.5-3 points higher; FIGURES, "
                             "issue 12)")
    parser.add_argument("--cell-local-density", action=argparse.BooleanOptionalAction, default=None,
                        help="cell detection, merged cells (more than 1 particle per parcel): a pair collides at "
                             "the solids fraction the coupling's deposit gives around its two parcels, not at its "
                             "cell's mean, which loses the collisions of clouds smaller than a cell (default: off; "
                             "on the rig it brings weight 8 closer to the CFD-DEM, 0.51 of its collisions and "
                             "v_y rms -1.5 %% against 0.47 and -5.1 %%, but leaves weight 64's v_y rms 11.6 %% low; "
                             "FIGURES, issue 12, thirtieth session)")
    parser.add_argument("--parcel-cloud", choices=("density", "weight"), default="density",
                        help="how wide a weighted parcel couples to the gas: density (default) = its real particles "
                             "at the number density of those around it (narrow in the dense streams), weight = one "
                             "particle per cell anywhere (the earlier rule; its weighted streams ran ~9 points of the "
                             "particles further downstream than weight 1 without collisions; FIGURES, issue 12)")
    parser.add_argument("--no-packing-stress", action="store_true",
                        help="cell detection: without the MP-PIC packing stress (on by default: the cell scheme's "
                             "parcels have no excluded volume)")
    parser.add_argument("--max-particles", type=int, default=None, help="cap the parcels released (CI)")
    parser.add_argument("--real-particles", type=int, default=None,
                        help="one size: real particles released over the paper's window (default: the paper's "
                             "parcels x --particles-per-parcel, 12,000 x W at 315 um); parcels = real / W. The "
                             "paper's second HEL run: 96000 (its DEM reference: 96000 at weight 1)")
    parser.add_argument("--monodisperse", action="store_true", help="all particles of the mean diameter")
    parser.add_argument("--gas-warmup", type=finite_float, default=0.01, help="gas-only time before release, s")
    parser.add_argument("--output-interval", type=finite_float, default=1e-3, help="time between snapshots, s")
    parser.add_argument("--seed", type=int, default=0, help="seed of the injection positions and sizes")
    parser.add_argument("--no-vtk", action="store_true", help="write run.zarr only")
    parser.add_argument("--no-gas-snapshots", action="store_true", help="no gas cell fields at output times")


def main(argv=None) -> int:
    from hel_warp.errors import HelWarpError

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_arguments(parser)
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    try:
        return run(args, progress=not args.no_progress)
    except HelWarpError as exc:
        print(f"colliding_streams: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
