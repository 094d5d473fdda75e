"""Host side of the ``cell`` detection of the ``surrogate`` strategy: stochastic parcel collisions per collision cell.

Bird's no-time-counter scheme per collision cell with the real number density (weights), Enskog's g0, a sampled
impact geometry and the contact-form surrogate outcome; the equations and their sources are in the header of
``kernels/cell_collide.py``. This module chooses the collision cells, owns the device arrays, mixes the run seed
with the step counter (deterministic for a seed; the pair ``(seed, step)`` is the whole random state, so a
checkpoint restarts exactly) and turns the device counters into the strategy's ``counts()``.

Collision cells (:class:`CellConfig`):

- a triply periodic box (``periodic_box``): a lattice that tiles the box, cells as close to cubic as the sides
  allow, sized to hold ``parcels_per_cell`` parcels on average (or of edge ``cell_size``), larger where heavy
  parcels' pairs would saturate (``automatic_edge``);
- with a HEL solver (``grid``, a ``hel_warp.parcels.coupling.GridSpec``): the grid cells, each cut into
  ``subdivision``^3 sub-cells, or merged ``coarsen``^3 (heavy parcels), shifted at random every sub-step; a cell's
  number density is taken over the fluid volume inside it (``CellConfig.fluid_volume``: merged or shifted cells
  reach into walls);
- otherwise the bounding box of the live parcels, cells of ``cell_size`` (or sized as the periodic box's).

Which anchor it follows, and where it differs (README "Cell detection"): Bird's NTC (SPARTA ``collide vss``:
candidates from the cell's (sigma g)_max, acceptance sigma g / (sigma g)_max) with the weighted parcels of
Schmidt & Rutland (2000, spray parcels: candidates with the largest weight, acceptance with the pair's), the
Enskog factor of Montanero & Santos (1996), and the momentum-exact min(w_i, w_j) impulse of the swept detection,
which for unequal weights is Boyd's (1996) conservative partial update, its energy deficit put back per block of
cells and weight class (``CellConfig.restore_energy``).
It differs from SPARTA in the majorant (an exact per-step bound from the cell's velocities, not a running
maximum; no remainder carried between steps), from O'Rourke (1981) in drawing pairs instead of a Poisson number
of collisions per parcel pair, and from Sommerfeld (2001) in colliding two real parcels of the cell rather than
a fictitious partner drawn from local statistics.
"""

from __future__ import annotations

import math
import sys
from typing import NamedTuple
from dataclasses import dataclass

import numpy as np

from hel_warp.errors import ConfigError
from hel_warp.collisions.pairs import DEFAULT_STREAMS, pair_counts

PARCELS_PER_CELL = 16.0
"""Default mean parcels per collision cell in a periodic box or the bounding box: enough pairs per cell that
N (N - 1) samples the pair density, few enough that partners stay within a few mean free paths at eps_s >= 0.01
(a cell of 16 parcels of weight 1 at eps_s = 0.05 is 2.6 mm = 8 d wide, ~4 mean free paths)."""
BATCHED_ROUNDS = 64
"""Batched forest rounds per step at most (one accepted pair per cell and round; the rest inline): most cells of a
gas finish within them, a dense MP-PIC cell with thousands of collisions per step does not hold the others up."""
BATCHED_MIN_ROWS = 32
"""A batched forest evaluation costs a block of 64 rows (``kernels/forest.py`` BLOCK_ROWS) however few are used; the
inline walk of one pair costs ~3 rows of a block on the CPU: below ~32 pairs a round, inline is as cheap."""
RESTORE_BLOCK = 2
"""Cells per axis of a block that restores the energy of unequal-weight events: 2^3 cells of ~16 parcels hold ~6
parcels of a species of 1 parcel in 20 (a 1/8-weight 315/475 um mixture at 30 % large by number), so a class
nearly never stands alone, while the block stays a few mean free paths wide."""
EPS_CAP = 0.55
"""Largest cell solids fraction put into Carnahan-Starling's g0 (it diverges at 1; MP-PIC cells can overfill)."""
APPROACH_REDRAW = 64
"""Draws of the pair an accepted, receding candidate hands its collision to under the approach filter (each must
have its two weights, approach and pass its own acceptance test): in a dense weighted gas 16 draws lose 1.5 % of the
collisions, 64 none measurable; a cell of passed streams, with no approaching pair, spends them on each accepted
candidate."""


@dataclass(frozen=True, kw_only=True)
class CellConfig:
    """Settings of the ``cell`` detection (validated at construction)."""

    local_density: bool = False
    """In merged grid cells (``coarsen`` > 1: heavy parcels on a HEL grid), a candidate pair's rate takes the real
    solids fraction around its two parcels instead of the cell's mean: the coupling's deposited eps_s at each
    parcel less its own share (w V_p sum S^2 / h^3 over its stencil S), e_ij their mean, chi_ij = g0(e_ij) e_ij /
    e_cell (e_cell the cell's fraction without the pair's mean share), so that a parcel collides at the density of
    the others around it. Unbiased in a uniform gas (the own share removed). Off by default: on the rig (96
    held-out seeds against 28 CFD-DEM seeds, ``hel_warp.studies.rig_ensemble``) it raises the real collisions from 0.47 to
    0.51 of the CFD-DEM's at weight 8 with the transverse spread closer (-1.5 % against -5.1 %), but at weight 64
    from 0.37 to 0.54 with the spread 11.6 % low (the default -4.2 %). Grid cells of weight 1 and periodic boxes are
    not merged and keep the cell's mean either way."""
    parcels_per_cell: float = PARCELS_PER_CELL
    """Mean parcels per cell the lattice is sized for (periodic box / bounding box; ignored with a grid); heavy
    parcels get larger cells where this many would saturate their pairs (``automatic_edge``)."""
    cell_size: float | None = None
    """Cell edge, m; overrides ``parcels_per_cell`` (periodic box / bounding box)."""
    subdivision: int = 1
    """Sub-cells per grid cell and axis with a HEL solver's grid (1: the grid cell)."""
    coarsen: int | None = None
    """Grid cells per collision cell and axis with a HEL solver's grid (k^3 grid cells merged into one). None: the
    smallest k that keeps a parcel pair of the largest weight from saturating, ``pair_saturation`` <=
    ``SATURATION_TARGET`` (h >= sqrt(w sigma / 0.2): 4 cells of the rig's 1 mm grid at weight 8), when a parcel
    weighs more than 1 and no subdivision is asked; else 1. Coarser cells average the number density over more
    volume: the collisions of dense clouds smaller than a cell are undercounted."""
    shift: bool | None = None
    """Shift the collision lattice by a random offset in [0, h)^3 every sub-step (Ihle & Kroll 2001's grid shift):
    whether two parcels can meet then depends on their separation only, not on where a fixed cell face falls (the
    rig's channel axis is a face of the merged 4 mm cells: the two streams would only meet once a parcel has
    crossed it). None: shift merged cells (``coarsen`` > 1), keep grid cells and periodic lattices as they are."""
    approaching: bool | None = None
    """True: a collision of a pair with a weighted parcel goes to a pair whose centres approach, (x_j - x_i) .
    (v_i - v_j) > 0, the colliding particle of a weighted parcel drawn from a cloud of (w - 1) V_p / eps_cell about
    its centre, a weighted pair that met within ``approach_memory`` exempt from the position test (its next real
    collision is with another particle of the cloud, which approaches one time in two: such a pair is eligible with
    probability 1/2; always eligible, it would meet again twice as often as plain NTC's pairs). Candidates are drawn and accepted as Bird's NTC; an accepted pair that recedes hands its
    collision to a pair of the cell with the same two weights, drawn until one approaches and passes its own
    acceptance (``approach_redraw``; after a draw of other weights the next is drawn among the parcels of the two
    weights, so that one weight-8 parcel among sixteen single particles finds its partners: drawn from the whole cell
    a weights 1 / 8 mixture lost 4-5 % of its 1-8 collisions): a cell collides as often as
    NTC says, and only a cell whose pairs all recede (two streams that have passed each other) collides less; a
    candidate whose weights find no approaching pair where other weights do collides itself. Pairs of single
    particles are not tested (their approach at the cell's scale reads the correlation their own collisions leave,
    not the flow: a weights 1 / 8 mixture lost 5 % of its small-small rate). On the rig
    (1e-3 s, 32-seed ensembles): weight 64 crossing +0.031 / +0.070 / +0.038 on three seed sets against plain NTC's
    +0.081 / +0.108 / +0.091, but v_y rms 5.6-7.0 % low against four CFD-DEM seeds; weight 8 -0.005 / -2.5 % and
    +0.015 / -5.9 %; the 315 / 475 um mixture at weights 8, 8: the 475 um class +0.002 / +2.8 % (plain +0.089 /
    +13.5 %). The homogeneous gas at weights 1 / 8 / 64, eps_s = 0.01 / 0.05, dt = 1e-3 / 1e-4 / 7.14e-5 s: within
    2 % of Enskog's frequency and 5 % of Haff's cooling (0.951-0.991). Off by default: it trades the crossing for
    the transverse spread, and plain NTC meets weight 8 on three seed sets.
    With the parcels' clouds (against 28 CFD-DEM seeds) it costs little transverse spread:
    weight 64 on 192 held-out seeds -0.025 / -0.4 % (sections 1-7 +0.007 / -0.8 %; the default +0.052 / +0.0 % there),
    but the dense weight-64 gas (eps_s = 0.05, 8,000 parcels) cools at 0.945-0.948 of Haff's rate (the default
    0.972), just past the 5 % target, so it stays off.
    None (default): on while a live parcel weighs more than 1 (with the collisional transfer:
    the weighted rig within 0.05 / 5 % of 28 CFD-DEM seeds on held-out seeds at weights 8 and 64, the homogeneous
    gas within 5 % of Enskog and Haff at weights 8 and 64, the weights 1 / 8 mixture's collisions per kind of pair
    as plain NTC's), off at weight 1 (the filter leaves pairs of single
    particles alone).
    False: any pair of the cell, whatever its positions (Bird's NTC, exact for the homogeneous gas)."""
    nearest: int = 0
    """> 0: nearest-neighbour partners (Bird 2007; SPARTA's ``collide_modify nearcp yes Nlimit``): each candidate's
    second parcel is the nearest to the first among up to ``nearest`` parcels of the cell (all when fewer), the
    first's last partner excluded; the acceptance is unchanged. 0: a uniformly drawn pair (Bird's NTC)."""
    packing_stress: bool = True
    """With a HEL solver: the MP-PIC packing stress (Harris & Crighton 1994; Snider 2001; OpenFOAM's
    ``HarrisCrighton``), tau = ``packing_pressure`` eps_s^``packing_beta`` / max(``packing_fraction`` - eps_s,
    1e-7 (1 - eps_s)) of the deposited solids fraction, as the parcels' a_coll = -grad tau / (eps_s rho_p). The cell
    detection has no excluded volume (parcels may overlap; DEM spheres and the swept detection's parcels may not):
    without it the rig's injection clouds overpack (eps_s > 1 in a 1 mm cell at dt = 1e-4 s; at 1e-3 s the
    collision rate of the weight-1 clouds, from their own snapshots, is 3-5x the CFD-DEM's in the supply channels
    and arms), over-collide and leave the holders too hot. On by default. With the trilinear
    coupling it took the rig at weight 8, dt = 1e-3 s (sixteen seeds against two CFD-DEM seeds) from +0.019 /
    +6.9 % to +0.005 / -0.4 % in crossing / v_y rms; beside the weight-scaled coupling tents (``GridSpec.spread``)
    it changes little there (seeds 0-7: +0.055 / -1.8 % with, +0.059 / -1.8 % without). At weight 1 and 1e-4 s
    both miss (+0.124 / +29 % with, +0.085 / +20 % without; the swept detection is weight 1's default). A periodic
    box (no grid) has no stress."""
    packing_pressure: float = 10.0
    """P_s of the packing stress, Pa (OpenFOAM's ``pSolid`` default)."""
    packing_beta: float = 2.0
    """beta of the packing stress (OpenFOAM's default)."""
    packing_fraction: float = 0.58
    """Close-packed solids fraction of the packing stress (OpenFOAM's ``alphaPacked``)."""
    enskog: bool = True
    """Enskog's factor g0 (Carnahan-Starling) of the cell's real solids fraction; False: Boltzmann (g0 = 1)."""
    eps_cap: float = EPS_CAP
    """Largest solids fraction put into g0."""
    log_capacity: int = 0
    """Accepted events logged per step (pair, g, sampled normal) for tests and diagnostics; 0: none."""
    cfl: float = 1.0
    """Largest path length of a parcel per sub-step, in cell edges: the step is cut into
    K = ceil(v_max dt / (cfl h_min)) sub-steps (at most ``max_substeps``)."""
    max_substeps: int = 64
    """Sub-steps per step at most (1: one sampling at the step's start positions, the plain NTC step)."""
    batched_rounds: int = BATCHED_ROUNDS
    """With a batched forest: rounds of one accepted pair per cell at most; the cells left over (dense ones) finish
    with inline tree walks."""
    batched_min_rows: int = BATCHED_MIN_ROWS
    """The batched rounds stop after a round of fewer pairs than this (the rest inline)."""
    restore_energy: bool = True
    """Parcels of unequal weight: put the energy the heavier parcel's partial impulse loses (against w_min real
    collisions) back into its weight class after each sub-step, as a random kick along the events' impulses
    (``kernels/cell_collide.py``, Boyd 1996); False: the partial impulse alone (too much dissipation: several times
    the collisions' own at e = 0.9)."""
    approach_memory: int = 16
    """With ``approaching``: accepted partners each parcel remembers (``CellArgs.recent_partners``); a weighted pair
    that met within them is exempt from the position test (its next real collision is with another particle of the
    partner's cloud, eligible one time in two). A pair that met keeps receding from each other until both have
    collided again, and in a dense gas that is more than the last partner: weight 64, eps_s = 0.05, dt = 1e-3 s,
    Enskog's frequency 0.924 / 0.941 / 0.956 / 0.952 of it remembering 1 / 4 / 16 / 64 partners."""
    approach_redraw: int = APPROACH_REDRAW
    """With ``approaching``: a candidate whose pair does not approach is drawn again from the cell, up to this many
    draws, and the approaching (or exempt) pair it finds is accepted at the plain NTC rate. A cell then collides as
    often as plain NTC says whatever share of its pairs approach (exactly so in expectation when that share is the
    homogeneous gas's half), and only a cell with almost no approaching pair, two streams that have passed each
    other, collides less. 0: a pair that does not
    approach is rejected and approaching ones collide at twice the rate: a dense gas, where pairs that have collided
    recede, then collides too little (0.956 of Enskog's frequency at weight 64, eps_s = 0.05)."""
    approach_events: float = 0.25
    """With ``approaching``: the step is also cut so that the last step's accepted events per parcel come to at most
    this many per sub-step. Within one sampling a parcel that has collided heads away from the partner it met,
    which sits on the cell-mates' side, so its later candidates of the sub-step approach less often than half: at
    weight 64, eps_s = 0.05, dt = 1e-3 s (1.1 events per parcel and step) the frequency fell to 0.87 of Enskog's;
    new positions (the paths advance between sub-steps) undo the bias."""
    fluid_volume: bool = True
    """With a HEL grid and its fluid mask: a collision cell's real number density (and g0's solids fraction) is
    taken over the fluid volume inside it (at least 1/8 of the cell), not its whole volume. A merged or shifted cell
    reaching into walls otherwise dilutes the density there: on the rig an 11 mm cell in a 4 x 8 mm supply channel
    is a quarter fluid. Cells of fluid grid cells alone (weight 1's lattice) are unchanged bit for bit. False: the
    whole volume."""
    wall_paths: bool = False
    """True: with a solver's walls and more than one sub-step, a sub-stepped path that crosses a wall is reflected
    there (``kernels/reflect.py``, the push's e_n, e_t and surface contact), its velocity with it, so that the next
    sub-steps sample the parcel on its side of the wall. False (default): the paths run straight through the walls
    for the whole step and the push reflects at its end. Measured on the rig (315 um, 1e-3 s, 32 seeds against the
    four CFD-DEM seeds): it brings the release streams' local granular
    temperature by the arms' walls from 2.5x to ~1.5x the CFD-DEM's, but moves every weight further from the CFD-DEM
    (weight 1 crossing +0.053 -> +0.061 and v_y rms +0.8 -> +11.2 %; weight 8 +0.070 / +4.2 %), so it stays off."""
    collisional_transfer: bool | None = None
    """None (default): on (``transfer``; with ``approaching`` too, whose redraw among the parcels of the candidate's
    two weights keeps a rare kind's collisions: drawn from the whole cell, a weights 1 / 8 mixture's 1-8 rate fell to
    0.92-0.94 of Enskog's with both). True: the Enskog collisional transfer of momentum across the contact distance (Alexander,
    Garcia & Alder 1995, "A consistent Boltzmann algorithm", PRL 74: 5212): after each event the two parcels' paths
    move apart along the sampled normal, parcel i back and j on, each by its mass share of c (r_i + r_j) times w_min
    / w, with c such that the new momenta carried across the displacements equal the real pair's collision virial
    (r_i + r_j) J.n ((1 + e) / e for smooth spheres; ``kernels/cell_collide.py`` ``transfer_scale``). Point parcels
    of the NTC scheme collide where they stand, so a dense cloud carries no collisional pressure (the excluded volume
    of DEM spheres and the swept detection's parcels); with the displacement it carries Enskog's, p_c = 2 (1 + e)
    eps^2 rho_p g0 Theta. The displacements give the parcels the hard-sphere gas's structure, so a cell's count
    varies as S N (S the Carnahan-Starling compressibility), not as Poisson's N, and NTC's N (N - 1) would count 2 %
    too few pairs at 16 parcels per cell and eps_s = 0.05: the pairs are counted as N (N - 1) + (1 - S) k N, k = 1 -
    (3/8) d sum 1 / L_a the share of a parcel's excluded-volume hole (radius d) that a cell of edges L_a holds
    (``cell_prepare``; it over-counts in cells of few parcels: +2 % at weight 1 and +5 % at weight 64 with 4 per
    cell, eps_s = 0.05). Measured (``cases/homogeneous_cooling.py``, ``hel_warp.studies.rig_ensemble``): the homogeneous gas at weights 1 / 8 / 64, eps_s = 0.01 / 0.05, dt = 1e-3 / 1e-4 / 7.14e-5 s within
    1.5 % of Enskog's frequency and within 5 % of Haff's cooling (weight 64, eps_s = 0.05: 0.945-0.979 over five
    seeds of the 1,000-parcel box, 0.966-0.973 in the 8,000-parcel box; plain NTC's weight 64 cools as slowly); the
    rig (315 um, 1e-3 s, against four CFD-DEM seeds, whole run / sections 1-7) weight 1 +0.019 / -4.1 % and +0.041 /
    -6.7 % with ~450,000 real collisions per run (CFD-DEM 451,366, plain NTC 881,045), weight 8 +0.027 / -4.3 % and
    +0.053 / -4.0 % (plain +0.041 / -2.8 % and +0.083 / -2.5 %), weight 64 +0.047 / -3.0 % and +0.076 / -4.4 % (plain
    +0.074 / -1.1 % and +0.101 / -1.7 %): the crossing closer at every weight, the transverse spread 1.5-3 points
    lower. False: positions untouched (Bird's NTC)."""
    restore_block: int = RESTORE_BLOCK
    """Collision cells per axis of a restoration block (the region whose parcels of one weight share a deficit)."""

    @property
    def transfer(self) -> bool:
        """Whether the collisional transfer is on (``collisional_transfer``, None resolved: on)."""
        if self.collisional_transfer is None:
            return True
        return bool(self.collisional_transfer)

    def approaching_at(self, w_max: float) -> bool:
        """Whether the approach filter is on in a step whose heaviest live parcel weighs ``w_max``
        (``approaching``, None resolved: on when ``w_max`` > 1)."""
        if self.approaching is None:
            return bool(w_max > 1.0)
        return bool(self.approaching)

    def __post_init__(self):
        if not (math.isfinite(self.parcels_per_cell) and self.parcels_per_cell >= 2.0):
            raise ConfigError(f"cell parcels_per_cell must be >= 2 (got {self.parcels_per_cell!r}): a cell needs "
                              "pairs")
        if self.cell_size is not None and not (math.isfinite(self.cell_size) and self.cell_size > 0.0):
            raise ConfigError(f"cell cell_size must be > 0 m (got {self.cell_size!r})")
        if int(self.subdivision) != self.subdivision or self.subdivision < 1:
            raise ConfigError(f"cell subdivision must be a positive integer (got {self.subdivision!r})")
        if self.coarsen is not None and (int(self.coarsen) != self.coarsen or self.coarsen < 1):
            raise ConfigError(f"cell coarsen must be a positive integer or None (got {self.coarsen!r})")
        if self.subdivision > 1 and self.coarsen not in (None, 1):
            raise ConfigError("cell subdivision and coarsen exclude each other: give one of them")
        if int(self.nearest) != self.nearest or self.nearest < 0:
            raise ConfigError(f"cell nearest must be an integer >= 0 (got {self.nearest!r}): parcels scanned for "
                              "the nearest partner, 0 for a random one")
        if self.approaching not in (None, True, False):
            raise ConfigError(f"cell approaching must be True, False or None (got {self.approaching!r})")
        if int(self.approach_memory) != self.approach_memory or self.approach_memory < 1:
            raise ConfigError(f"cell approach_memory must be a positive integer (got {self.approach_memory!r})")
        if int(self.approach_redraw) != self.approach_redraw or self.approach_redraw < 0:
            raise ConfigError(f"cell approach_redraw must be an integer >= 0 (got {self.approach_redraw!r})")
        if not (math.isfinite(self.approach_events) and self.approach_events > 0.0):
            raise ConfigError(f"cell approach_events must be > 0 (got {self.approach_events!r})")
        if not 0.0 < self.eps_cap < 1.0:
            raise ConfigError(f"cell eps_cap must lie in (0, 1) (got {self.eps_cap!r})")
        if not (math.isfinite(self.cfl) and self.cfl > 0.0):
            raise ConfigError(f"cell cfl must be > 0 (got {self.cfl!r})")
        if int(self.max_substeps) != self.max_substeps or self.max_substeps < 1:
            raise ConfigError(f"cell max_substeps must be a positive integer (got {self.max_substeps!r})")
        if int(self.batched_rounds) != self.batched_rounds or self.batched_rounds < 1:
            raise ConfigError(f"cell batched_rounds must be a positive integer (got {self.batched_rounds!r})")
        if int(self.batched_min_rows) != self.batched_min_rows or self.batched_min_rows < 0:
            raise ConfigError(f"cell batched_min_rows must be an integer >= 0 (got {self.batched_min_rows!r})")
        if int(self.restore_block) != self.restore_block or self.restore_block < 1:
            raise ConfigError(f"cell restore_block must be a positive integer (got {self.restore_block!r})")
        if int(self.log_capacity) != self.log_capacity or self.log_capacity < 0:
            raise ConfigError(f"cell log_capacity must be an integer >= 0 (got {self.log_capacity!r})")


class _LoopState(NamedTuple):
    """The sub-step loop's device state (``kernels/cell_collide.py`` ``substep_plan``)."""

    state: object
    """(3,) int32: sub-step index, sub-steps of the step, the step's seed (``LOOP_*``)."""
    more: object
    """(1,) int32: 1 while a sub-step is left (the while node's condition)."""
    sub_seed: object
    """(1,) int32: the sub-step's seed."""
    sub_dt: object
    """(1,) float32: the sub-step, s."""
    events: object
    """(1,) float64: the last step's accepted events per parcel."""


def _launch_key(value):
    """What a launch bakes in of ``value`` (a Warp struct, array or plain value), hashable: arrays by address and
    shape, structs field by field (``CellCollisions``' captured loop is captured again when it changes)."""
    import warp as wp

    if isinstance(value, wp.array):
        return ("array", int(value.ptr or 0), tuple(value.shape), str(value.device))
    cls = getattr(value, "_cls", None)
    if cls is not None and hasattr(cls, "vars"):
        return tuple((name, _launch_key(getattr(value, name))) for name in cls.vars)
    try:
        return tuple(float(v) for v in value)
    except TypeError:
        return value


def step_seed(seed: int, step: int) -> int:
    """The kernel seed of step ``step`` of a run seeded ``seed``: splitmix64 of the pair, 31 bits (int32 >= 0)."""
    z = (int(seed) * 0x9E3779B97F4A7C15 + int(step) + 0x632BE59BD9B4E019) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF
    return int((z ^ (z >> 31)) & 0x7FFFFFFF)


def unsaturated_edge(w_max: float, r_max: float) -> float:
    """The smallest cube edge h with ``pair_saturation`` <= ``SATURATION_TARGET`` for a parcel pair of weight w_max
    and radius r_max (0 at weight 1: single particles do not saturate)."""
    if w_max <= 1.0:
        return 0.0
    return math.sqrt(pair_saturation(w_max, r_max, (1.0, 1.0, 1.0)) / SATURATION_TARGET)  # it goes as 1 / h^2


def automatic_edge(volume: float, n_parcels: int, parcels_per_cell: float, w_max: float, r_max: float) -> float:
    """The edge of a cube holding ``parcels_per_cell`` of ``n_parcels`` parcels spread over ``volume``, or the
    unsaturated edge if that is larger (heavy parcels; grids coarsen by the same rule, ``unsaturated_coarsening``).
    At 16 parcels per cell the saturation grows as w^(1/3): weight 64 at eps_s = 0.05 had 0.42 and cooled 0.972 of
    Haff over 8 seeds, 0.992 in the unsaturated cells (``cases/homogeneous_cooling.py``)."""
    edge = (float(volume) * parcels_per_cell / max(n_parcels, 1)) ** (1.0 / 3.0)
    return max(edge, unsaturated_edge(w_max, r_max))


def periodic_lattice(box, n_parcels: int, parcels_per_cell: float, cell_size: float | None, w_max: float = 1.0,
                     r_max: float = 0.0):
    """(origin, cell edges, shape) of a lattice tiling the periodic ``box``: edge ``cell_size`` or
    ``automatic_edge`` (``parcels_per_cell`` parcels per cube, no saturated heavy pairs), rounded so whole cells
    fill each side."""
    box = np.asarray(box, np.float64)
    if cell_size is None:
        cell_size = automatic_edge(float(np.prod(box)), n_parcels, parcels_per_cell, w_max, r_max)
    shape = np.maximum(1, np.round(box / cell_size)).astype(int)
    return np.zeros(3), box / shape, shape


def grid_lattice(grid, subdivision: int, coarsen: int = 1):
    """(origin, cell edges, shape) of a HEL grid's cells cut into ``subdivision``^3 sub-cells, or merged by
    ``coarsen``^3 (the last collision cell of an axis may reach past the grid)."""
    s, k = int(subdivision), int(coarsen)
    h = float(grid.spacing) * k / s
    return np.asarray(grid.origin, np.float64), np.full(3, h), -(-np.asarray(grid.shape, int) * s // k)


def unsaturated_coarsening(grid_spacing: float, w_max: float, r_max: float) -> int:
    """The smallest k >= 1 with w_max pi (2 r_max)^2 / (k h)^2 <= SATURATION_TARGET (``pair_saturation`` of cubic
    cells of edge k h)."""
    return max(1, math.ceil(unsaturated_edge(w_max, r_max) / grid_spacing * (1.0 - 1e-9)))


def bounding_lattice(x: np.ndarray, pad: float, parcels_per_cell: float, cell_size: float | None,
                     w_max: float = 1.0, r_max: float = 0.0):
    """(origin, cell edges, shape) over the bounding box of ``x`` (padded by ``pad``): edge ``cell_size`` or
    ``automatic_edge`` over the box."""
    lo = x.min(axis=0) - pad
    hi = x.max(axis=0) + pad
    extent = np.maximum(hi - lo, 2.0 * pad)
    if cell_size is None:
        cell_size = automatic_edge(float(np.prod(extent)), len(x), parcels_per_cell, w_max, r_max)
    shape = np.maximum(1, np.ceil(extent / cell_size)).astype(int)
    return lo, np.full(3, cell_size), shape


SATURATION_TARGET = 0.2
"""``pair_saturation`` that the automatic coarsening of a HEL grid's collision cells aims below (``CellConfig.coarsen``):
the beams then exchange 0.98 of weight 1's momentum (``tests/test_cell_collisions.py``)."""
SATURATION_WARN = 0.3
"""``pair_saturation`` above which the cell detection warns once per run: two cold counter-streaming beams of
weight-w parcels exchange 2 % / 17 % / 33 % less momentum than kinetic theory's at 0.16 / 0.62 / 1.25."""


def pair_saturation(w_max: float, r_max: float, edges) -> float:
    """w_max sigma_max h_max / V of the collision cells (sigma_max = pi (2 r_max)^2): the expected collisions of a
    parcel pair of the largest weight while it crosses a cell side by side (the cell's real number density of one
    parcel, w / V, times sigma times the path h). NTC collides a parcel pair with the rate of w real partners, but
    each collision turns the whole partner parcel: once this nears 1 the pair collides again with its own
    deflected self instead of fresh partners, and the momentum exchange saturates below kinetic theory's (the
    Bird / O'Rourke schemes assume it << 1)."""
    e = [float(x) for x in edges]
    return w_max * math.pi * (2.0 * r_max) ** 2 * max(e) / (e[0] * e[1] * e[2])


class CellCollisions:
    """NTC collisions per cell for a ``SurrogateCollision`` (``detection="cell"``); see the module docstring.

    ``collide(particles, dt, forest, domain, periodic_box=..., grid=...)`` changes ``particles.v`` in place (the
    positions are the caller's: the parcels then fly with their new velocities); ``counts()`` the last call's
    counters; ``state()`` / ``set_state()`` the random state (seed, steps taken).
    """

    def __init__(self, *, config: CellConfig | None = None, seed: int = 0, n_streams: int = DEFAULT_STREAMS):
        if int(seed) != seed or seed < 0:
            raise ConfigError(f"seed must be an integer >= 0 (got {seed!r})")
        self.config = config if config is not None else CellConfig()
        self.seed = int(seed)
        self.steps = 0
        """Collision steps taken (the second half of the random state)."""
        self.n_streams = int(n_streams)
        self._args = None
        self._key = None
        self._counts = None
        self.lattice = None
        """(origin, cell edges, shape) of the last step."""
        self._substeps = 0
        self.pair_saturation = 0.0
        """Of the last step: w_max pi (2 r_max)^2 h_max / V, the collisions a parcel pair of the largest weight
        and size meets while it crosses one collision cell together (``pair_saturation``)."""
        self._saturation_warned = False
        self._shift_pending = False
        self._recent = None
        """(N, R) each parcel's last accepted partners (``CellArgs.recent_partners``), kept across steps."""
        self._pending_recent = None
        """A restored ``cell_recent_partners`` waiting for the arrays to be allocated."""
        self.approaching = False
        """Whether the last step ran the approach filter (``CellConfig.approaching_at`` its heaviest parcel)."""
        self._events_per_parcel = 0.0
        self._fluid = None
        """(fluid mask array, its integral F on the device) of the last HEL grid (``fluid_integral``)."""
        self._loop = None
        """The sub-step loop's device state (``_LoopState``), allocated per device by :meth:`_loop_arrays`."""
        self._loop_graphs = {}
        """Captured sub-step loops of the device loop, by what their launches bake in."""
        self._on_device = False
        """True while the last step's sub-steps and events per parcel live on the device (the device loop), not in
        :attr:`substeps` / :attr:`events_per_parcel`'s host values."""
        self.device_loop_steps = 0
        """Steps whose sub-steps ran as the captured device loop (no read-back)."""

    @property
    def substeps(self) -> int:
        """Sub-steps of the last step (read from the device after a device-loop step)."""
        if self._on_device and self._loop is not None:
            from kernels.cell_collide import LOOP_SUBSTEPS

            return int(self._loop.state.numpy()[LOOP_SUBSTEPS])
        return self._substeps

    @substeps.setter
    def substeps(self, value: int) -> None:
        self._substeps = int(value)

    @property
    def events_per_parcel(self) -> float:
        """Accepted events per live parcel (each event counted for both parcels) of the last step: with
        ``approaching`` it sets the next step's sub-steps (``CellConfig.approach_events``); in the checkpoint (read
        from the device after a device-loop step)."""
        if self._on_device and self._loop is not None:
            return float(self._loop.events.numpy()[0])
        return self._events_per_parcel

    @events_per_parcel.setter
    def events_per_parcel(self, value: float) -> None:
        self._events_per_parcel = float(value)
        if self._loop is not None:
            self._loop.events.fill_(float(value))

    def _device_loop_ok(self, device) -> bool:
        """Whether the sub-step loop can be a captured while loop here: the CPU (Warp's graphs), or CUDA with graph
        conditional nodes (CUDA 12.4+); else, and after a graph the driver refused, the host loop (one warning)."""
        import warp as wp

        if getattr(self, "_device_loop_refused", False):
            return False
        if wp.get_device(device).is_cuda and not wp.is_conditional_graph_supported():
            self._refuse_device_loop("this driver lacks CUDA graph conditional nodes (CUDA 12.4+)")
            return False
        return True

    def _refuse_device_loop(self, why: str) -> None:
        self._device_loop_refused = True
        print(f"hel-warp: warning: cell detection: the sub-steps loop on the host, reading the device each step: {why}",
              file=sys.stderr)

    def _loop_arrays(self, device):
        """The sub-step loop's device state (:attr:`_loop`), allocated once per device; the host's events per parcel
        written into it."""
        import warp as wp

        if self._loop is None or str(self._loop.state.device) != str(device):
            self._leave_device()
            self._loop = _LoopState(wp.zeros(3, dtype=wp.int32, device=device),
                                    wp.zeros(1, dtype=wp.int32, device=device),
                                    wp.zeros(1, dtype=wp.int32, device=device),
                                    wp.zeros(1, dtype=wp.float32, device=device),
                                    wp.full(1, self._events_per_parcel, dtype=wp.float64, device=device))
            self._loop_graphs = {}
        return self._loop

    def _leave_device(self) -> None:
        """Bring the device loop's sub-steps and events per parcel back to the host values (a host-loop step
        follows)."""
        if self._on_device:
            self._substeps = self.substeps
            self._events_per_parcel = self.events_per_parcel
            self._on_device = False

    # ------------------------------------------------------------------ device arrays
    def _allocate(self, particles, n_cells: int, spin_form: bool = False) -> None:
        import warp as wp

        from kernels.cell_collide import N_COUNTS, CellArgs

        memory = int(self.config.approach_memory) if self.approaching else 1
        key = (str(particles.device), particles.count, n_cells, bool(spin_form), memory)
        if self._key == key:
            return
        self._loop_graphs = {}  # their launches hold the arrays replaced here
        dev = particles.device
        n = particles.count
        cap = int(self.config.log_capacity)
        a = CellArgs()
        a.cell_key = wp.zeros(2 * n, dtype=wp.int32, device=dev)
        a.cell_slot = wp.zeros(2 * n, dtype=wp.int32, device=dev)
        a.cell_start = wp.zeros(n_cells, dtype=wp.int32, device=dev)
        a.cell_end = wp.zeros(n_cells, dtype=wp.int32, device=dev)
        a.cell_sigma_g_max = wp.zeros(n_cells, dtype=wp.float32, device=dev)
        a.cell_candidates = wp.zeros(n_cells, dtype=wp.float32, device=dev)
        n_features, n_targets = (8, 5) if spin_form else (6, 2)
        a.spin_form = 1 if spin_form else 0
        a.features = wp.zeros((n_cells, n_features), dtype=wp.float32, device=dev)
        a.batch_features = wp.zeros((n_cells, n_features), dtype=wp.float32, device=dev)
        a.batch_out = wp.zeros((n_cells, n_targets), dtype=wp.float32, device=dev)
        a.batch_count = wp.zeros(1, dtype=wp.int32, device=dev)
        a.cell_rng = wp.zeros(n_cells, dtype=wp.uint32, device=dev)
        a.cell_remaining = wp.zeros(n_cells, dtype=wp.int32, device=dev)
        a.cell_bound = wp.zeros(n_cells, dtype=wp.float32, device=dev)
        a.cell_solids = wp.zeros(n_cells, dtype=wp.float32, device=dev)
        a.pending_row = wp.full(n_cells, -1, dtype=wp.int32, device=dev)
        a.pending_pair = wp.zeros(n_cells, dtype=wp.vec2i, device=dev)
        a.pending_normal = wp.zeros(n_cells, dtype=wp.vec3, device=dev)
        a.cell_fluid_volume = wp.zeros(n_cells, dtype=wp.float32, device=dev)
        a.use_fluid = 0
        a.fluid_integral = wp.zeros((1, 1, 1), dtype=wp.float64, device=dev)  # none until a grid's mask is given
        a.particle_deficit = wp.zeros(n, dtype=wp.mat33, device=dev)
        a.particle_spin_deficit = wp.zeros(n, dtype=wp.mat33, device=dev)
        self._no_omega = wp.zeros(1, dtype=wp.vec3, device=dev)
        self._no_eps = wp.zeros(1, dtype=wp.float32, device=dev)
        self._eps_local = None
        if self._recent is None or self._recent.shape != (n, memory) or str(self._recent.device) != str(dev):
            ring = np.full((n, memory), -1, np.int32)
            pending = self._pending_recent if self._pending_recent is not None else (
                self._recent.numpy() if self._recent is not None else None)
            if pending is not None and pending.shape[0] == n:  # a restored or kept ring, cut or padded to R
                k = min(memory, pending.shape[1])
                ring[:, :k] = pending[:, :k]
            self._pending_recent = None
            self._recent = wp.array(ring, dtype=wp.int32, device=dev)
        a.recent_partners = self._recent
        self._more = wp.zeros(1, dtype=wp.int32, device=dev)
        from kernels.cell_collide import CellArgs

        self._args_store = wp.empty(1, dtype=CellArgs, device=dev)
        """The ``CellArgs`` on the device for the cell kernels (``kernels.cell_collide.collide_cells``)."""
        self._round = wp.zeros(1, dtype=wp.int32, device=dev)
        self._rounds = wp.zeros(1, dtype=wp.int32, device=dev)
        self._path = wp.zeros(n, dtype=wp.vec3, device=dev)
        self._path_start = wp.zeros(n, dtype=wp.vec3, device=dev)
        self._shift = wp.zeros(n, dtype=wp.vec3, device=dev)
        self._wall_hits = wp.zeros(1, dtype=wp.int32, device=dev)
        a.counts = wp.zeros(N_COUNTS, dtype=wp.int32, device=dev)
        s2 = self.n_streams * self.n_streams
        a.calls = wp.zeros(s2, dtype=wp.int32, device=dev)
        a.collisions = wp.zeros(s2, dtype=wp.int32, device=dev)
        a.log_count = wp.zeros(1, dtype=wp.int32, device=dev)
        a.log_pair = wp.zeros(cap, dtype=wp.vec2i, device=dev)
        a.log_g = wp.zeros(cap, dtype=wp.vec3, device=dev)
        a.log_normal = wp.zeros(cap, dtype=wp.vec3, device=dev)
        self._args = a
        self._key = key

    def choose_lattice(self, particles, *, periodic_box=None, grid=None, reach: float = 0.0,
                       extremes: tuple[float, float, int] | None = None):
        """(origin, cell edges, shape) of this step's collision cells (see the module docstring); ``reach``: the
        largest path length of the step (pads the bounding box); ``extremes``: (w_max, r_max, live count) when the
        caller has them (``Particles.live_extremes``). The positions are read back only where a bounding box needs
        them."""
        cfg = self.config
        self._merged = False
        if extremes is None:
            extremes = particles.live_extremes()[1:4]
        w_max, r_max, n_alive = extremes
        if not n_alive:
            w_max, r_max = 1.0, 0.0
        if periodic_box is not None:
            return periodic_lattice(periodic_box, n_alive, cfg.parcels_per_cell, cfg.cell_size, w_max, r_max)
        if grid is not None:
            k = cfg.coarsen
            if k is None:
                k = 1
                if w_max > 1.0 and cfg.subdivision == 1:
                    k = unsaturated_coarsening(float(grid.spacing), w_max, r_max)
            self._merged = k > 1
            return grid_lattice(grid, cfg.subdivision, k)
        x = particles.x.numpy()[particles.alive.numpy() != 0].astype(np.float64)
        return bounding_lattice(x, r_max + reach, cfg.parcels_per_cell, cfg.cell_size, w_max, r_max)

    # ------------------------------------------------------------------ one step
    def fluid_integral(self, fluid, device):
        """F[i, j, k] = fluid cells of ``fluid`` (a HEL grid's int mask, (nx, ny, nz)) in [0, i) x [0, j) x [0, k),
        float64 on ``device``; computed once per mask."""
        import warp as wp

        if self._fluid is not None and self._fluid[0] is fluid and str(self._fluid[1].device) == str(device):
            return self._fluid[1]
        mask = (fluid.numpy() if hasattr(fluid, "numpy") else np.asarray(fluid)) != 0
        f = np.zeros(tuple(int(n) + 1 for n in mask.shape), np.float64)
        f[1:, 1:, 1:] = mask.astype(np.float64).cumsum(0).cumsum(1).cumsum(2)
        self._fluid = (fluid, wp.array(f, dtype=wp.float64, device=device))
        return self._fluid[1]

    def collide(self, particles, dt: float, forest, domain, *, batch_forest=None, periodic_box=None, grid=None,
                apply: bool = True, particle_spin: bool = False, spin_form: bool = False, fluid=None, walls=None,
                extremes: tuple | None = None, local=None, device_extremes: tuple | None = None) -> None:
        """The step's collisions of ``particles`` (velocities in place); ``forest`` an explicit-layout ``Forest``,
        ``domain`` its ``ContactDomain``; ``batch_forest`` (perfect layout, optional): the accepted pairs predicted
        in batched rounds (faster, same pairs). ``apply=False``: selection only (counts and log; velocities
        unchanged). ``particle_spin``: collisions at the contact point (``particles.omega`` read and turned);
        ``spin_form``: the forest is a ``contact_spin`` model (8 features, 3 targets). ``fluid``: with ``grid``, its
        fluid mask (int, (nx, ny, nz)): a collision cell's number density is then taken over the fluid volume inside
        it, not its whole volume (a merged or shifted cell reaching into walls; ``CellConfig.fluid_volume``).
        ``walls``: (``SdfShapes``, ``WallParams``) of the solver: the sub-stepped paths reflect where they cross a
        wall, the velocities with them (``CellConfig.wall_paths``). ``extremes``: (max |v|, max weight, max radius,
        count) of the live parcels when the caller has them, else ``Particles.live_extremes`` here (one read-back).
        ``local``: (the coupling's ``CellGrid``, ``parcel_eps_s``) of the step, the solids fraction the deposit gives
        each parcel: in merged grid cells a pair's rate then takes it (``CellConfig.local_density``).

        ``device_extremes``: (the (5,) float64 device array ``Particles.launch_live_extremes`` filled, (max weight,
        max radius, live count) as host upper bounds) instead of ``extremes``: the sub-steps are then planned on the
        device from its largest speed, and where the lattice needs no positions (a grid's or a periodic box's,
        unshifted) and the paths no walls (``CellConfig.wall_paths`` off) they run as one captured graph whose while
        node loops over them, with no read-back (``HelConfig.read_back`` 'output'); elsewhere the extremes are read
        and the host loops. Both loops launch the same kernels with the same seeds and sub-step: the same bits."""
        import warp as wp

        from kernels.cell_collide import (LOOP_SUBSTEPS, advance_paths, collide_cells, fill_fluid_volumes, path_shifts,
                                          restore_energy, sort_by_cell, substep_begin, substep_end, substep_events,
                                          substep_plan)

        if dt is None or not (dt > 0 and math.isfinite(dt)):
            raise ConfigError(f"cell detection needs the step dt > 0 (got {dt!r})")
        self._counts = None
        self._shift_pending = False
        store = None
        if device_extremes is not None:
            store, (w_max, r_max, n_alive) = device_extremes
            v_max = None
        else:
            if extremes is None:
                extremes = particles.live_extremes()[:4]
            v_max, w_max, r_max, n_alive = extremes
        seed = step_seed(self.seed, self.steps)
        self.steps += 1
        cfg = self.config
        lattice = None
        device_loop = n_alive >= 2 and store is not None and (periodic_box is not None or grid is not None) and not (
            walls is not None and cfg.wall_paths) and self._device_loop_ok(particles.device)
        if device_loop:  # the lattice from the bounds; a shifted one draws each sub-step's offset on the host
            lattice = self.choose_lattice(particles, periodic_box=periodic_box, grid=grid,
                                          extremes=(w_max, r_max, n_alive))
            device_loop = not (cfg.shift if cfg.shift is not None else self._merged)
        if store is not None and not device_loop and n_alive >= 2:  # the host loop: the exact extremes (its
            # lattice, reach and K; bounds below 2 parcels need no read)
            v_max, w_max, r_max, n_alive = particles.live_extremes()[:4]
            store, lattice = None, None
        n_alive = int(n_alive)
        if n_alive < 2:
            self._leave_device()
            self._zero_counts()
            return
        if lattice is None:
            lattice = self.choose_lattice(particles, periodic_box=periodic_box, grid=grid, reach=v_max * dt,
                                          extremes=(w_max, r_max, n_alive))
        origin, edges, shape = lattice
        shift = cfg.shift if cfg.shift is not None else self._merged
        if shift and periodic_box is None:
            shape = np.asarray(shape, int) + 1  # a shifted lattice reaches one cell further on every axis
        n_cells = int(np.prod(shape))
        if n_cells >= 2**31 - 1:
            raise ConfigError(f"{n_cells} collision cells do not fit int32 keys: give a larger cell_size")
        self.lattice = (origin, edges, shape)
        self.pair_saturation = pair_saturation(w_max, r_max, edges)
        # weight 1: a parcel is one particle, so no parcel meets its own deflected self and no lower weight exists;
        # the saturation is then the dense regime of particles comparable to the cell (a packed bed's), not an artefact
        if self.pair_saturation > SATURATION_WARN and w_max > 1.0 and not self._saturation_warned:
            self._saturation_warned = True
            print(f"hel-warp: warning: cell detection: a parcel pair of weight {w_max:g} meets "
                  f"{self.pair_saturation:.2g} collisions while it crosses one collision cell of "
                  f"{1e3 * float(np.max(edges)):.3g} mm (w sigma h / V > {SATURATION_WARN:g}): the pair collides with "
                  "itself and the momentum it exchanges saturates (too little: two counter-streaming beams lose "
                  "17 % of their exchange at 0.62); use a lower weight or coarser collision cells", file=sys.stderr)
        self.approaching = approaching = cfg.approaching_at(w_max)
        self._allocate(particles, n_cells, spin_form)
        a = self._args
        if not device_loop:
            self._leave_device()
        loop, more, sub_seed, sub_dt, events = self._loop_arrays(particles.device)
        path_cell = cfg.cfl * float(np.min(edges))
        substeps = 0  # planned on the device
        if device_loop and not self._on_device:  # the host's events per parcel of the last step, for the plan
            events.fill_(self._events_per_parcel)
        if not device_loop:
            substeps = max(1, math.ceil(v_max * dt / path_cell))
            if approaching:
                substeps = max(substeps, math.ceil(self.events_per_parcel / cfg.approach_events - 1e-9))
            substeps = int(min(cfg.max_substeps, substeps))
            self.substeps = substeps
        wp.launch(substep_plan, dim=1, device=particles.device,
                  inputs=[events if store is None else store, events, wp.float64(dt),  # host K: no extremes read
                          wp.float64(path_cell), int(cfg.max_substeps), 1 if approaching else 0,
                          wp.float64(cfg.approach_events), int(substeps), int(seed)],
                  outputs=[loop, more, sub_dt])
        wp.copy(self._path, particles.x)
        a.particle_x, a.particle_radius = self._path, particles.radius
        a.particle_density, a.particle_weight = particles.density, particles.weight
        a.particle_alive, a.particle_stream = particles.alive, particles.stream
        a.spin = 1 if particle_spin else 0
        a.particle_omega = particles.omega if particle_spin else self._no_omega
        a.n_streams = self.n_streams
        a.origin = tuple(float(v) for v in origin)
        a.cell_size = tuple(float(v) for v in edges)
        a.shape = tuple(int(v) for v in shape)
        a.cell_volume = float(np.prod(edges))
        a.periodic = 1 if periodic_box is not None else 0
        a.use_fluid = 0
        if fluid is not None and grid is not None and periodic_box is None and self.config.fluid_volume:
            a.use_fluid = 1
            a.fluid_integral = self.fluid_integral(fluid, particles.device)
            a.fluid_origin = tuple(float(v) for v in grid.origin)
            a.fluid_spacing = float(grid.spacing)
        a.sub_dt, a.sub_seed = sub_dt, sub_seed
        a.enskog = 1 if self.config.enskog else 0
        a.approaching = 1 if approaching else 0
        a.approach_redraw = int(cfg.approach_redraw) if approaching else 0
        a.nearest = int(self.config.nearest)
        a.eps_cap = float(self.config.eps_cap)
        a.apply = 1 if apply else 0
        a.transfer = 1 if cfg.transfer else 0  # the count's correction even when only selecting
        a.local_density = 0
        a.particle_eps_local = self._no_eps
        if local is not None and self._merged and cfg.local_density:
            from kernels.cell_collide import local_solids

            if self._eps_local is None or self._eps_local.shape[0] != particles.count:
                self._eps_local = wp.zeros(particles.count, dtype=wp.float32, device=particles.device)
            local_solids(local[0], particles, local[1], self._eps_local)
            a.local_density = 1
            a.particle_eps_local = self._eps_local
        a.domain = domain
        self._zero_counts()
        self._rounds.zero_()
        self._wall_hits.zero_()
        # the parcels' paths are advanced here (and their shift handed to the push) when there are sub-steps or the
        # transfer moves them; the device loop, not knowing K, always does (one sub-step without the transfer: the
        # path ends at x + v dt, the shift is 0 exactly)
        paths = device_loop or substeps > 1 or (cfg.transfer and apply)
        reflect = walls is not None and cfg.wall_paths and substeps > 1 and apply
        if reflect:
            from kernels.reflect import reflect_at_walls

        def substep():
            wp.launch(substep_begin, dim=1, device=particles.device, inputs=[loop], outputs=[sub_seed])
            fill_fluid_volumes(a)
            sort_by_cell(a)
            collide_cells(a, forest, particles.v, self._more, self._round, self._rounds, batch_forest=batch_forest,
                          max_rounds=cfg.batched_rounds, min_rows=cfg.batched_min_rows, args_store=self._args_store)
            if apply and cfg.restore_energy:
                restore_energy(a, particles.v, int(cfg.restore_block))
            if paths:
                if reflect:
                    wp.copy(self._path_start, self._path)
                advance_paths(self._path, particles.v, particles.alive, sub_dt)
                if reflect:  # the wall between the sub-steps, as the push meets it at the step's end
                    reflect_at_walls(walls[0], walls[1], particles.alive, self._path, particles.v, self._wall_hits,
                                     particles.radius, particle_x_start=self._path_start,
                                     particle_omega=particles.omega)
            wp.launch(substep_end, dim=1, device=particles.device, inputs=[loop], outputs=[more])

        if device_loop:
            key = (_launch_key(a), _launch_key(particles.v), _launch_key(particles.omega), id(forest), id(batch_forest),
                   id(self._args_store), bool(apply), bool(cfg.restore_energy), int(cfg.restore_block),
                   int(cfg.batched_rounds), int(cfg.batched_min_rows))
            cached = self._loop_graphs.get(key)
            if cached is None:
                if len(self._loop_graphs) >= 8:  # a lattice that keeps changing: keep the newest few
                    self._loop_graphs.pop(next(iter(self._loop_graphs)))
                try:
                    with wp.ScopedCapture(device=particles.device, force_module_load=False) as capture:
                        wp.capture_while(more, substep)
                    # the objects keyed by id() are held with their graph, so no other object can take their id
                    cached = (capture.graph, (forest, batch_forest, self._args_store, particles))
                except RuntimeError as exc:  # a graph the driver will not build: nothing of the step has run
                    if not wp.get_device(particles.device).is_cuda:
                        raise
                    self._refuse_device_loop(f"the CUDA graph could not be created ({str(exc).splitlines()[0][:120]})")
                    cached = None
                if cached is not None:
                    self._loop_graphs[key] = cached
            if cached is not None:
                wp.capture_launch(cached[0])
                self.device_loop_steps += 1
            else:  # the host loop after all, over the K the device planned (read back)
                for _ in range(int(loop.numpy()[LOOP_SUBSTEPS])):
                    substep()
            self._on_device = True  # K and the events per parcel (below) are the device's
        else:
            for k in range(substeps):
                if shift:  # the sub-step's random lattice offset, from the step's seed (restart-exact)
                    offset = (np.random.default_rng((step_seed(seed, k), 0x5EED)).uniform(0.0, 1.0, 3)
                              * np.asarray(edges))
                    a.origin = tuple(float(v) for v in np.asarray(origin) - offset)
                    self.lattice = (np.asarray(origin) - offset, edges, shape)
                substep()
        if paths:
            path_shifts(self._path, particles.x, particles.v, particles.alive, float(dt), self._shift)
            self._shift_pending = True
        if approaching:
            if device_loop:
                wp.launch(substep_events, dim=1, device=particles.device, inputs=[a.counts, store], outputs=[events])
            else:
                from kernels.cell_collide import COUNT_ACCEPTED

                accepted = int(a.counts.numpy()[COUNT_ACCEPTED])
                self._events_per_parcel = 2.0 * accepted / max(n_alive, 1)

    def correct_positions(self, particles) -> None:
        """After the caller moved the parcels by v dt (the push): add the sub-stepped paths' position changes
        (once; a no-op after a host-loop step of one sub-step without the transfer; after the device loop's the
        change added is 0)."""
        if not self._shift_pending:
            return
        from kernels.collide import launch_add_shift  # the swept detection's x += shift

        launch_add_shift(self._shift, particles.alive, particles.x)
        self._shift_pending = False

    def _zero_counts(self) -> None:
        if self._args is None:
            return
        a = self._args
        for arr in (a.counts, a.calls, a.collisions, a.log_count):
            arr.zero_()

    # ------------------------------------------------------------------ results
    def count_arrays(self):
        """The device arrays :meth:`counts` reads, ({name: wp.array}, {}) (``SurrogateCollision.count_arrays``);
        None before the first step."""
        if self._args is None:
            return None
        return {"cell_counts": self._args.counts, "calls": self._args.calls, "collisions": self._args.collisions,
                "rounds": self._rounds, "wall_hits": self._wall_hits}, {}

    def counts_from(self, host: dict, extras: dict) -> dict:
        """:meth:`counts` from host copies of :meth:`count_arrays`."""
        from kernels.cell_collide import (COUNT_ACCEPTED, COUNT_CANDIDATES, COUNT_CELLS, COUNT_CLAMPED,
                                          COUNT_COULOMB, COUNT_ENERGY, COUNT_LOG_OVERFLOW, COUNT_OVER_MAX,
                                          COUNT_RESTORED, COUNT_SEPARATION, COUNT_UNRESTORED)

        s = self.n_streams
        c = np.asarray(host["cell_counts"]).astype(np.int64)
        calls = np.asarray(host["calls"]).reshape(s, s).astype(np.int64)
        collisions = np.asarray(host["collisions"]).reshape(s, s).astype(np.int64)
        return {"collisions": int(collisions.sum()), "surrogate_calls": int(calls.sum()),
                "detected_pairs": 0, "cell_candidates": int(c[COUNT_CANDIDATES]),
                "cell_accepted": int(c[COUNT_ACCEPTED]), "cell_over_max": int(c[COUNT_OVER_MAX]),
                "cell_cells": int(c[COUNT_CELLS]), "cell_log_overflow": int(c[COUNT_LOG_OVERFLOW]),
                "cell_restored": int(c[COUNT_RESTORED]), "cell_unrestored": int(c[COUNT_UNRESTORED]),
                "rounds": int(host["rounds"][0]), "cell_wall_hits": int(host["wall_hits"][0]),
                "guard_separation": int(c[COUNT_SEPARATION]), "guard_coulomb": int(c[COUNT_COULOMB]),
                "guard_energy": int(c[COUNT_ENERGY]), "guard_domain_clamped": int(c[COUNT_CLAMPED]),
                **pair_counts("collisions", collisions), **pair_counts("surrogate_calls", calls)}

    def counts(self) -> dict:
        """``collisions`` (real binary collisions: sum of min(w_i, w_j)), ``surrogate_calls`` (accepted events),
        ``detected_pairs`` (0: no overlap test), ``rounds`` (batched forest rounds), ``cell_candidates``, ``cell_accepted``, ``cell_over_max``
        (candidates above the majorant, accepted with probability 1), ``cell_cells`` (cells with >= 2 parcels),
        ``cell_log_overflow``, ``cell_wall_hits`` (paths reflected at walls between sub-steps), ``cell_restored`` / ``cell_unrestored`` (weight classes of a block whose unequal-weight
        energy deficit was put back / could not be), ``guard_separation|coulomb|energy|domain_clamped``, per stream pair
        ``collisions_<a>_<b>``, ``surrogate_calls_<a>_<b>``."""
        if self._counts is not None:
            return dict(self._counts)
        staged = self.count_arrays()
        if staged is None:
            from kernels.cell_collide import N_COUNTS

            s = self.n_streams
            host = {"cell_counts": np.zeros(N_COUNTS, np.int64), "calls": np.zeros(s * s, np.int64),
                    "collisions": np.zeros(s * s, np.int64), "rounds": [0], "wall_hits": [0]}
            self._counts = self.counts_from(host, {})
        else:
            self._counts = self.counts_from({k: a.numpy() for k, a in staged[0].items()}, staged[1])
        return dict(self._counts)

    def event_log(self) -> dict:
        """The last step's logged events (host copies): ``pair`` (k, 2) parcel slots, ``g`` (k, 3) pre-collision
        v_i - v_j, ``normal`` (k, 3) sampled contact normals; k = min(accepted, log_capacity). Sub-steps and rounds
        are logged in order, and each cell's events in its order; the cells of one launch interleave in their
        threads' order (fixed on the CPU, varying from run to run on CUDA)."""
        if self._args is None:
            return {"pair": np.zeros((0, 2), np.int32), "g": np.zeros((0, 3)), "normal": np.zeros((0, 3))}
        a = self._args
        k = min(int(a.log_count.numpy()[0]), a.log_pair.shape[0])
        return {"pair": a.log_pair.numpy()[:k].copy(), "g": a.log_g.numpy()[:k].copy(),
                "normal": a.log_normal.numpy()[:k].copy()}

    def cell_arrays(self) -> dict:
        """The last step's per-cell arrays (host copies): ``start``, ``end`` (ranges in ``slot``), ``slot`` (live
        parcel slots in cell order), ``sigma_g_max`` (the majorant, m^3/s), ``candidates`` (expected M)."""
        a = self._args
        n = a.particle_x.shape[0]
        return {"start": a.cell_start.numpy().copy(), "end": a.cell_end.numpy().copy(),
                "slot": a.cell_slot.numpy()[:n].copy(), "sigma_g_max": a.cell_sigma_g_max.numpy().copy(),
                "candidates": a.cell_candidates.numpy().copy()}

    def state(self) -> dict:
        """The random state: ``cell_seed`` and ``cell_steps`` (numpy scalars), ``cell_recent_partners`` (each parcel's
        last accepted partners, (N, R) int32, newest first; empty before the first step) and
        ``cell_events_per_parcel``: the checkpoint's."""
        recent = (self._recent.numpy().copy() if self._recent is not None
                  else np.zeros((0, 1), np.int32) if self._pending_recent is None else self._pending_recent.copy())
        return {"cell_seed": np.array(self.seed, np.int64), "cell_steps": np.array(self.steps, np.int64),
                "cell_recent_partners": recent,
                "cell_events_per_parcel": np.array(self.events_per_parcel, np.float64)}

    def set_state(self, state: dict) -> None:
        """Restore :meth:`state` (entries missing: left as they are)."""
        if "cell_seed" in state:
            self.seed = int(np.asarray(state["cell_seed"]))
        if "cell_steps" in state:
            self.steps = int(np.asarray(state["cell_steps"]))
        recent = state.get("cell_recent_partners")
        if recent is None and "cell_last_partner" in state:  # a checkpoint from before the ring: its one column
            recent = np.asarray(state["cell_last_partner"], np.int32).reshape(-1, 1)
        if recent is not None:
            recent = np.asarray(recent, np.int32)
            recent = recent.reshape(recent.shape[0], -1) if recent.size else recent.reshape(0, 1)
            if self._recent is not None and self._recent.shape == recent.shape:
                self._recent.assign(recent)
            else:  # put in place when the arrays are allocated (an empty one: none yet)
                self._recent = None
                self._pending_recent = recent if recent.size else None
        if "cell_events_per_parcel" in state:
            self.events_per_parcel = float(np.asarray(state["cell_events_per_parcel"]))
