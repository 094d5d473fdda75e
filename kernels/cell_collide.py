"""Stochastic parcel collisions per collision cell: Bird's no-time-counter (NTC) scheme with the surrogate outcome.

What it computes (docs/developer/architecture.md "Collision detection", ``cell``; docs/physics/references.md "Stochastic collisions of
parcels"): parcels of weight w (real particles per parcel) collide with the frequency of the REAL number density,
whatever w. Per collision cell of volume V holding N parcels, in one step dt:

- candidates (Bird 1994, sec. 11.1, NTC; SPARTA ``collide vss``; weighted as Schmidt & Rutland 2000 for spray
  parcels): ``M = 1/2 N (N - 1) w_max chi_max (sigma g)_max dt / V``, drawn as floor(M) plus one with
  probability frac(M) (no remainder carried between steps: the cell lists change every step);
- each candidate is a uniformly drawn pair (i != j) of the cell, accepted with probability
  ``sigma_ij g_ij max(w_i, w_j) chi_ij / ((sigma g)_max w_max chi_max)``, sigma_ij = pi (r_i + r_j)^2,
  g_ij = |v_i - v_j| with the velocities as left by the cell's earlier collisions of the step (the majorant
  thinning of a Poisson process: an unbiased sample of the collision process over the step at any dt);
- Enskog's factor (dense gas; Montanero & Santos 1996, "Monte Carlo simulation method for the Enskog
  equation"): ``chi_ij = g0(eps_ij)``, Carnahan-Starling g0, eps_ij the real solids fraction of the cell
  WITHOUT the two candidates (sum_k w_k V_k - w_i V_i - w_j V_j) / V, so that with Poisson cell counts the
  expected rate is ``1/2 n^2 sigma <g> g0(eps)`` exactly for g0 linear in eps; chi_max = g0 of the whole cell
  bounds it (g0 grows with eps). ``enskog = 0``: chi = 1 (Boltzmann);
- the density around the pair (``local_density``; ``CellConfig.local_density``, merged grid cells of heavy
  parcels): ``chi_ij = g0(e_ij) e_ij / e_cell``, e_ij the mean of the two parcels' ``particle_eps_local`` (the
  coupling's deposited eps_s at the parcel less its own share, ``local_solids_kernel``) and e_cell the cell's
  real solids fraction less the pair's mean share: each parcel collides at the density of the others around it,
  not at the cell's mean (a 10 mm cell averages the rig's clouds; in a uniform gas E[e_ij] = e_cell).
  chi_max = g0(e_max) e_max / (e_cell less the largest share) bounds it;
- the majorant: sigma_max = pi (2 r_max)^2 of the cell, g_max = 2 max_k |v_k - c| (c the cell's mean velocity:
  |v_i - v_j| <= |v_i - c| + |v_j - c|), w_max the cell's largest weight. A collision can raise a parcel's
  distance from c (by up to sqrt 2 for equal masses), so a later candidate may exceed the bound; it is then
  accepted and counted (``over_max``: the bias, measured ~0);
- the approach filter (``approaching``; ``CellConfig.approaching``, on by default for weighted parcels): an accepted
  candidate with a weighted parcel whose centres do not approach, (x_j - x_i) . (v_i - v_j) <= 0 (a weighted parcel's
  colliding particle drawn from its cloud; a weighted pair that met recently eligible one time in two), hands its
  collision to another pair of the cell with the same two weights, drawn until one approaches and passes its own
  acceptance test (at most ``approach_redraw`` draws; a draw of other weights is followed by one among the parcels of
  the candidate's two weights, ``draw_of_weight``, so that a kind of pair rare in its cell, one weight-8 parcel among
  sixteen single particles, finds its partners as often as a common one). The cell's expected total stays NTC's,
  placed on approaching pairs of each kind in proportion to their rates; a cell in which no pair approaches (two
  streams that have passed each other) does not collide, and a candidate whose kind finds no approaching pair
  where other kinds do collides itself, so that each kind of pair keeps its count. Pairs of single particles are not
  tested: at the cell's scale their approach reads the correlation their own collisions leave (a pair that
  collided recedes from its cell-mates too), not the flow. ``approach_redraw`` = 0: the doubled-rate rule instead
  (every receding pair rejected, approaching ones at twice the rate against twice the majorant), which loses
  collisions in a dense gas where pairs that have collided recede;
- optionally (``nearest`` > 0; Bird 2007's nearest-neighbour collisions, SPARTA's ``collide_modify nearcp``) the
  second parcel of a candidate is the nearest to the first among up to ``nearest`` of the cell, the first's last
  partner excluded; the acceptance is the same (the partner's g is a random pair's where positions carry no
  information on velocities, so Enskog's frequency stays);
- impact geometry of an accepted pair: the impact parameter uniform in b^2 on [0, (r_i + r_j)^2] and a uniform
  azimuth about g (docs/physics/references.md "Impact parameter"): ``n = cos(chi) g_hat + sin(chi) (cos(phi) e1 + sin(phi)
  e2)``, sin^2(chi) = b^2 / (r_i + r_j)^2, so g.n = |g| cos(chi) > 0 (approaching), n from i to j;
- outcome: the contact-form forest on the features clamped into its training domain, through the
  admissibility guard (``kernels/forest.py``), the impulse of one representative real pair J
  (``contact_impulse``), applied with the weighted rule of the swept detection: min(w_i, w_j) real binary
  collisions, parcel i gets ``-min(w_i, w_j) J`` and j ``+min(w_i, w_j) J`` (dv_i = -(w_min/w_i) J/m_i). Momentum
  ``sum w m v`` is conserved to round-off. With the acceptance factor max(w_i, w_j) every real particle of
  either parcel meets on average the right number of partners (the lighter parcel's particles one full
  collision per event, the heavier's a fraction w_min/w_max of one). For w_i != w_j the heavier parcel's partial
  impulse alone would lose more energy than w_min binary collisions, which the next item puts back;
- parcels of unequal weight (Boyd 1996, "Conservative species weighting scheme for the direct simulation Monte
  Carlo method", J. Thermophys. Heat Transfer 10: 579): the heavier parcel's partial update v + (w_min/w) J/m is
  Boyd's momentum-conserving one, and it loses energy that w_min real collisions keep: the spread the impulse J
  would give w_min of the parcel's w particles, ``deficit = w_min (1 - w_min/w) |J|^2 / (2 m)`` per event. At
  e = 0.9 that is several times the collision's own dissipation (1 - e^2) mu g_n^2 / 2 (315/475 um, weights 1/8:
  3.8x with the large parcel the heavier, 13x with the small one), so without a remedy a mixture of weights cools
  several times too fast. What is lost is not only an energy but a second moment along the impulse: the w_min
  real collisions give the parcel's particles sum (v v^T) a term w_min |J|^2 / m J^ J^ (J^ = J / |J|), the
  partial impulse only (w_min / w) of it. Each parcel keeps that missing part as a tensor, T = sum over its events
  of deficit J^ J^ (trace: the deficit), and it is put back after each sub-step (``cell_restore``) as the random
  spread it is: per block of ``restore_block``^3 cells and per weight class of parcels carrying a deficit, every
  parcel of the class gets a normal kick of covariance 2 T / M (along its impulses, expected energy its own
  deficit), less the class's mass-weighted mean kick (momentum exact), scaled so that the kicks' own energy is the
  class's deficits D; the class's velocities about their block mean are then scaled by alpha ~ 1 so that the class
  gains exactly D (the kicks' cross term with the velocities, zero in expectation, is not left in the energy). So
  momentum is exact, the energy is that of the w_min real collisions and stays with the weight class (in a
  mixture of per-species weights: the species) that would have had it, and the class's velocity tensor gains
  what the real collisions' would, in expectation. An isotropic kick of scale s, the root of sum M (s v.delta + s^2 |delta|^2 / 2) = D that is ~2 |v.delta| / |delta|^2 when v.delta < 0
  and D is small against the class's energy, would mirror the parcels' velocities about random planes
  whatever D was, isotropizing the heavier class at every sub-step (a box with T_x = 3 T_y = 3 T_z, weights 1,8:
  the 475 um class would keep 0.45 of the anisotropy T_x / T_yz - 1 that weight 1 keeps, against 1.1 along the
  impulses; on the 315 / 475 um rig at weights 1,8 its transverse spread would come out 19 % short of the
  CFD-DEM's, against +1.5 %; ``tests/test_species_weights.py``). A deterministic rescaling of the class's
  velocities about its mean keeps the energy too but not the tensor: the smallest-kick root of the same
  equation, which acts as one, leaves the box 1.6 times the anisotropy weight 1 keeps. Measured
  (``cases/homogeneous_cooling.py`` with ``--particles-per-parcel 1,8``): mixture cooling and each species' Theta within a few per cent of
  the weight-1 run, not within their statistical error (the 475 um species ends too hot whichever species is
  heavier, +9 % at weights 1,8 with the approach filter and +6 % without: mostly a light parcel meeting the same
  few heavy parcels of its cell again and again, where its real particle would meet W times as many distinct
  ones). A class with a single parcel in its block cannot take it
  (``unrestored``: that event keeps the loss; counted).

Sub-steps: a parcel must not fly past a cell within one collision sampling (DSMC's rule that dt be small against
the cell transit time; at dt = 1e-3 s a parcel of 5 m/s crosses five 1 mm cells). The step is cut into K
sub-steps, K = ceil(v_max dt / (cfl h_min)); each samples the cells from the positions along the parcels' straight
paths at its start (collisions change the later path: ``path_advance`` with the new velocity), with dt / K. The
end of the sub-stepped path differs from the push's x + v_final dt by ``shift`` (``path_shift``), added after the
push as the swept detection's in-step corrections are.

Threads: one per collision cell; a cell's candidates are resolved in order by its thread (they share parcels),
cells are disjoint. The forest is evaluated either inline (explicit tree walks in the cell's thread) or, faster,
in rounds: each cell stops at its next accepted pair, all cells' pairs are predicted in one batched evaluation
(``kernels/forest.py`` ``eval_forest``, perfect layout), applied, and the cells go on; the same pairs in the same
order either way. Random numbers: ``wp.rand_init(seed, cell)`` with a per-sub-step seed mixed on the device from
the host's per-step seed and the sub-step index (``substep_begin``), so a run is deterministic for a seed and
restarts exactly from (seed, step). Parcel lists: a stable radix sort of the live
parcels by cell (``wp.utils.radix_sort_pairs``), cell ranges from the sorted keys. Counts are integer atomics
(deterministic totals). The optional event log (fixed capacity, overflow counted) records the sampled geometry
for tests and diagnostics.

Launch wrappers at the bottom; they never allocate (hel_warp/collisions/cells.py owns the arrays).
"""

from __future__ import annotations

import warp as wp

from kernels.collide import forest_target, stream_pair_index
from kernels.forest import (GUARD_COULOMB, GUARD_ENERGY, GUARD_SEPARATION, ContactDomain, Forest, admissible_impulse,
                            contact_point_velocity, contact_spin_impulse, spin_guard, spin_kick, turn_spins,
                            write_contact_spin_features_in_domain,
                            contact_impulse, sphere_mass, write_contact_features_in_domain)
from kernels.interp import CellGrid, parcel_cell, parcel_stencil

COUNT_CANDIDATES, COUNT_ACCEPTED, COUNT_OVER_MAX, COUNT_CELLS = 0, 1, 2, 3
COUNT_SEPARATION, COUNT_COULOMB, COUNT_ENERGY, COUNT_CLAMPED, COUNT_LOG_OVERFLOW = 4, 5, 6, 7, 8
COUNT_RESTORED, COUNT_UNRESTORED = 9, 10
N_COUNTS = 11
FLUID_VOLUME_FLOOR = wp.constant(0.125)
"""Least share of a collision cell's volume that ``cell_fluid_volumes`` gives it: a cell nearly all wall would put
its few parcels into a sliver's volume (a density estimate of one or two parcels, and pairs far past saturation)."""
REDRAW_CLASS_TRIES = wp.constant(8)
"""Uniform draws per cell parcel at most when the approach filter redraws a parcel of a given weight
(``draw_of_weight``): a weight held by one parcel of the cell is missed with probability e^-8."""
"""``counts`` slots: candidates drawn, accepted events, candidates above the majorant, occupied cells (>= 2
parcels), guard corrections (separation, Coulomb, energy), domain clamps, events not logged (log full), weight
classes of a block whose energy deficit was restored / could not be (a single parcel of the class there)."""


@wp.struct
class CellArgs:
    """Everything the cell kernels read (arrays on one device); built by hel_warp/collisions/cells.py."""

    particle_x: wp.array(dtype=wp.vec3)
    """(N,) parcel centres along their paths at the sub-step's start, m (the cells are found from these)."""
    particle_radius: wp.array(dtype=wp.float32)
    """(N,) radii of one real particle, m."""
    particle_density: wp.array(dtype=wp.float32)
    """(N,) kg/m^3."""
    particle_weight: wp.array(dtype=wp.float32)
    """(N,) real particles per parcel."""
    particle_alive: wp.array(dtype=wp.int32)
    particle_stream: wp.array(dtype=wp.int32)
    particle_omega: wp.array(dtype=wp.vec3)
    """Spins, rad/s (read and updated when ``spin`` is 1)."""
    spin: wp.int32
    """1: collisions at the contact point (kernels/collide.py ``SweptArgs.spin``)."""
    spin_form: wp.int32
    """1: a ``contact_spin`` model (8 features, 3 targets; kernels/collide.py ``SweptArgs.spin_form``)."""
    n_streams: wp.int32
    origin: wp.vec3
    """Lower corner of the cell lattice, m."""
    cell_size: wp.vec3
    """Cell edge per axis, m (a periodic box: side / cells, the lattice tiles it)."""
    shape: wp.vec3i
    """Cells per axis; a parcel outside the lattice is counted in the nearest cell."""
    periodic: wp.int32
    """1: the lattice tiles a periodic box [origin, origin + shape * cell_size): positions are wrapped into it."""
    cell_volume: wp.float32
    """Volume of one cell, m^3."""
    use_fluid: wp.int32
    """1: a cell's volume is the fluid volume inside it (``cell_fluid_volume``, from a HEL grid's fluid mask); 0:
    ``cell_volume`` for every cell."""
    fluid_integral: wp.array3d(dtype=wp.float64)
    """(nx + 1, ny + 1, nz + 1) with ``use_fluid``: F[i, j, k] = fluid grid cells in [0, i) x [0, j) x [0, k); F is
    trilinear inside a grid cell, so the fluid volume of any box is exact from it (``box_fluid_cells``)."""
    fluid_origin: wp.vec3d
    """Lower corner of the HEL grid, m."""
    fluid_spacing: wp.float64
    """HEL grid spacing, m."""
    cell_fluid_volume: wp.array(dtype=wp.float32)
    """(n_cells,) with ``use_fluid``: the fluid volume of each collision cell, m^3 (``cell_fluid_volumes``)."""
    sub_dt: wp.array(dtype=wp.float32)
    """(1,) the sub-step's dt, s (``substep_plan``: the step's dt over its sub-steps)."""
    sub_seed: wp.array(dtype=wp.int32)
    """(1,) the sub-step's seed (``substep_begin``: the step's seed, which the host mixes from the run seed and the
    step counter, mixed with the sub-step index)."""
    local_density: wp.int32
    """1: a pair's rate takes the real solids fraction around its two parcels (``particle_eps_local``) instead of
    the cell's mean, for cells coarser than the coupling's deposit."""
    particle_eps_local: wp.array(dtype=wp.float32)
    """(N,) with ``local_density``: the deposited solids fraction at the parcel without its own share."""
    enskog: wp.int32
    """1: Enskog's factor chi = g0 (Carnahan-Starling); 0: chi = 1 (Boltzmann)."""
    approaching: wp.int32
    """1: only a pair whose centres approach, (x_j - x_i) . (v_i - v_j) > 0, collides (``approach_redraw``); 0: any
    pair of the cell (Bird's NTC)."""
    approach_redraw: wp.int32
    """With ``approaching``: > 0, candidates are drawn and accepted as NTC, and an accepted pair with a weighted
    parcel that does not approach hands its collision to a pair of the same two weights drawn again until one
    approaches (or is exempt) and passes its own acceptance, at most this many draws (the cell's NTC total kept
    however many of its pairs approach); 0: every pair that does not approach is rejected and approaching ones
    collide at twice the rate (twice the majorant)."""
    nearest: wp.int32
    """> 0: the partner of the first drawn parcel is the nearest of up to ``nearest`` parcels of the cell (all of
    them when the cell holds fewer), its last partner excluded (Bird 2007's nearest-neighbour collisions; SPARTA's
    ``collide_modify nearcp``); 0: a uniformly drawn second parcel (Bird's NTC)."""
    eps_cap: wp.float32
    """Largest solids fraction put into g0 (Carnahan-Starling diverges at 1; an MP-PIC cell can overfill)."""
    apply: wp.int32
    """1: resolve accepted pairs with the forest; 0: selection only (counts and log, velocities unchanged)."""
    transfer: wp.int32
    """1: collisional transfer (Alexander, Garcia & Alder 1995's consistent Boltzmann algorithm): an accepted pair's
    paths ``particle_x`` move apart along the sampled normal, each parcel by its mass share of c times the contact
    distance times w_min / w (``transfer_scale``, ``collisional_displacement``); 0: the positions are untouched
    (Bird's NTC)."""
    domain: ContactDomain
    cell_key: wp.array(dtype=wp.int32)
    """(2N,) radix-sort keys: cell index of each slot (dead: n_cells), sorted in place."""
    cell_slot: wp.array(dtype=wp.int32)
    """(2N,) radix-sort values: slots, in cell order after the sort."""
    cell_start: wp.array(dtype=wp.int32)
    """(n_cells,) first position of the cell in the sorted slots."""
    cell_end: wp.array(dtype=wp.int32)
    """(n_cells,) one past its last (start = end: empty)."""
    cell_sigma_g_max: wp.array(dtype=wp.float32)
    """(n_cells,) the majorant (sigma g)_max of the step, m^3/s (diagnostics, tests)."""
    cell_candidates: wp.array(dtype=wp.float32)
    """(n_cells,) the expected candidate count M of the step (before the integer draw)."""
    features: wp.array2d(dtype=wp.float32)
    """(n_cells, 6) inline mode: scratch feature row of each cell's thread."""
    batched: wp.int32
    """1: accepted pairs are resolved in rounds, one per cell and round, with one batched forest evaluation per
    round (``eval_forest``, perfect layout); 0: inline tree walks (explicit layout), one round."""
    batch_features: wp.array2d(dtype=wp.float32)
    """(n_cells, 6) the round's feature rows (compact: the first ``batch_count[0]``)."""
    batch_out: wp.array2d(dtype=wp.float32)
    """(n_cells, 2) the forest's two targets of each row."""
    batch_count: wp.array(dtype=wp.int32)
    """(1,) rows of the round."""
    cell_rng: wp.array(dtype=wp.uint32)
    """(n_cells,) random state of each cell's sequence (carried across the step's rounds)."""
    cell_remaining: wp.array(dtype=wp.int32)
    """(n_cells,) candidates still to draw in the step."""
    cell_bound: wp.array(dtype=wp.float32)
    """(n_cells,) the acceptance bound (sigma g)_max w_max chi_max, m^3/s."""
    cell_solids: wp.array(dtype=wp.float32)
    """(n_cells,) real solids volume sum w V of the cell, m^3."""
    pending_row: wp.array(dtype=wp.int32)
    """(n_cells,) batch row of the cell's accepted pair this round, -1: none."""
    pending_pair: wp.array(dtype=wp.vec2i)
    pending_normal: wp.array(dtype=wp.vec3)
    recent_partners: wp.array2d(dtype=wp.int32)
    """(N, R) each parcel's last R accepted partners, newest first (-1: none), written when ``approaching`` or
    ``nearest`` reads them (R = ``CellConfig.approach_memory`` with the filter, else 1); kept across steps (the
    checkpoint's). ``nearest`` leaves out column 0 (the last partner), the filter's ``met`` exemption reads every column."""
    particle_deficit: wp.array(dtype=wp.mat33)
    """(N,) the second moment the parcel's partial impulses lost this sub-step against w_min real collisions, as a
    tensor: sum over its events of the energy lost times J^ J^ (J^ the impulse's direction), J; its trace is the
    energy (0 for a parcel never the heavier of its pairs); restored and zeroed by ``cell_restore``."""
    particle_spin_deficit: wp.array(dtype=wp.mat33)
    """(N,) the same for the spins (``spin``): the rotational energy the parcel's partial spin kicks lost against
    w_min real collisions, as a tensor along the one-collision spin changes (trace: the energy), J; restored as a
    random spin kick along them (``restore_spin``) and zeroed by ``cell_restore``."""
    counts: wp.array(dtype=wp.int32)
    """(N_COUNTS,) integer counters of the step (slots above)."""
    calls: wp.array(dtype=wp.int32)
    """(n_streams^2,) accepted events per stream pair (min, max)."""
    collisions: wp.array(dtype=wp.int32)
    """(n_streams^2,) real binary collisions per stream pair: sum of round(min(w_i, w_j))."""
    log_count: wp.array(dtype=wp.int32)
    """(1,) events offered to the log."""
    log_pair: wp.array(dtype=wp.vec2i)
    """(capacity,) parcels (i, j) of each logged event (capacity 0: no log)."""
    log_g: wp.array(dtype=wp.vec3)
    """(capacity,) pre-collision relative velocity v_i - v_j, m/s."""
    log_normal: wp.array(dtype=wp.vec3)
    """(capacity,) sampled contact normal (from i to j)."""


@wp.func
def carnahan_starling(eps: float, eps_cap: float):
    """g0 = (1 - eps/2) / (1 - eps)^3 (Carnahan & Starling 1969), eps clamped to [0, eps_cap]."""
    e = wp.clamp(eps, 0.0, eps_cap)
    one = 1.0 - e
    return (1.0 - 0.5 * e) / (one * one * one)


@wp.func
def local_factor(eps_local: float, eps_minus: float, enskog: int, eps_cap: float):
    """The pair's rate over the cell's NTC rate without Enskog: the others' solids fraction around the pair over
    the cell's without the pair (number densities, one size), times g0 of the local fraction (Enskog)."""
    if eps_minus <= 0.0:
        return float(0.0)
    chi = eps_local / eps_minus
    if enskog != 0:
        chi = chi * carnahan_starling(eps_local, eps_cap)
    return chi


@wp.func
def compressibility(eps: float, eps_cap: float):
    """S = (1 - eps)^4 / (1 + 4 eps + 4 eps^2 - 4 eps^3 + eps^4): the hard-sphere gas's structure factor at zero
    wave number (Carnahan-Starling compressibility, k T dn/dp), the variance of a large cell's count over its mean;
    eps clamped to [0, eps_cap]."""
    e = wp.clamp(eps, 0.0, eps_cap)
    return wp.pow(1.0 - e, 4.0) / (1.0 + 4.0 * e + 4.0 * e * e - 4.0 * e * e * e + e * e * e * e)


@wp.func
def fluid_integral_at(f: wp.array3d(dtype=wp.float64), g: wp.vec3d):
    """F at the grid coordinates g (clamped into the grid): trilinear between F's nodes, which is exact."""
    nx = f.shape[0] - 1
    ny = f.shape[1] - 1
    nz = f.shape[2] - 1
    x = wp.clamp(g[0], wp.float64(0.0), wp.float64(nx))
    y = wp.clamp(g[1], wp.float64(0.0), wp.float64(ny))
    z = wp.clamp(g[2], wp.float64(0.0), wp.float64(nz))
    i = wp.min(int(x), nx - 1)
    j = wp.min(int(y), ny - 1)
    k = wp.min(int(z), nz - 1)
    fx = x - wp.float64(i)
    fy = y - wp.float64(j)
    fz = z - wp.float64(k)
    one = wp.float64(1.0)
    c00 = f[i, j, k] * (one - fx) + f[i + 1, j, k] * fx
    c10 = f[i, j + 1, k] * (one - fx) + f[i + 1, j + 1, k] * fx
    c01 = f[i, j, k + 1] * (one - fx) + f[i + 1, j, k + 1] * fx
    c11 = f[i, j + 1, k + 1] * (one - fx) + f[i + 1, j + 1, k + 1] * fx
    return (c00 * (one - fy) + c10 * fy) * (one - fz) + (c01 * (one - fy) + c11 * fy) * fz


@wp.func
def box_fluid_cells(f: wp.array3d(dtype=wp.float64), lo: wp.vec3d, hi: wp.vec3d):
    """Fluid grid-cell volumes (in cells) inside the box [lo, hi) of grid coordinates: inclusion-exclusion of F."""
    total = wp.float64(0.0)
    for corner in range(8):
        g = lo
        sign = wp.float64(1.0)
        for ax in range(3):
            if (corner >> ax) & 1 == 1:
                g[ax] = hi[ax]
            else:
                sign = -sign
        total += sign * fluid_integral_at(f, g)
    return total


@wp.kernel
def cell_fluid_volumes(args: CellArgs):
    """``cell_fluid_volume`` of each collision cell: the fluid volume of its box, m^3. A cell whose box lies wholly
    in fluid cells reads ``cell_volume`` itself (the plain lattice of fluid grid cells keeps its bits)."""
    cell = wp.tid()
    nyz = args.shape[1] * args.shape[2]
    idx = wp.vec3i(cell / nyz, (cell / args.shape[2]) % args.shape[1], cell % args.shape[2])
    lo = wp.vec3d(0.0, 0.0, 0.0)
    hi = wp.vec3d(0.0, 0.0, 0.0)
    for ax in range(3):
        edge = wp.float64(args.cell_size[ax])
        lo[ax] = (wp.float64(args.origin[ax]) + wp.float64(idx[ax]) * edge - args.fluid_origin[ax]) / args.fluid_spacing
        hi[ax] = lo[ax] + edge / args.fluid_spacing
    full = (hi[0] - lo[0]) * (hi[1] - lo[1]) * (hi[2] - lo[2])
    fluid = box_fluid_cells(args.fluid_integral, lo, hi)
    volume = args.cell_volume
    if fluid < full * wp.float64(1.0 - 1.0e-6):
        fluid = wp.max(fluid, full * wp.float64(FLUID_VOLUME_FLOOR))
        volume = wp.float32(fluid * args.fluid_spacing * args.fluid_spacing * args.fluid_spacing)
    args.cell_fluid_volume[cell] = volume


@wp.func
def cell_volume_of(args: CellArgs, cell: int):
    """The volume the cell's number density is taken over: its fluid volume (``use_fluid``) or ``cell_volume``."""
    if args.use_fluid != 0:
        return args.cell_fluid_volume[cell]
    return args.cell_volume


@wp.func
def sphere_volume(r: float):
    return (4.0 / 3.0) * wp.pi * r * r * r


@wp.func
def sample_normal(g: wp.vec3, u_b2: float, u_phi: float):
    """Contact normal of a random impact of relative velocity g: b^2 / (r_i + r_j)^2 = u_b2 (uniform in b^2),
    azimuth 2 pi u_phi about g_hat; returns n = cos(chi) g_hat + sin(chi) e(phi), sin^2(chi) = u_b2."""
    g_hat = wp.normalize(g)
    axis = wp.vec3(1.0, 0.0, 0.0)
    if wp.abs(g_hat[0]) > 0.57:
        axis = wp.vec3(0.0, 1.0, 0.0)
    e1 = wp.normalize(wp.cross(g_hat, axis))
    e2 = wp.cross(g_hat, e1)
    sin_chi = wp.sqrt(wp.clamp(u_b2, 0.0, 1.0))
    cos_chi = wp.sqrt(wp.max(1.0 - u_b2, 0.0))
    phi = 2.0 * wp.pi * u_phi
    return wp.normalize(cos_chi * g_hat + sin_chi * (wp.cos(phi) * e1 + wp.sin(phi) * e2))


@wp.kernel
def cell_keys(
    args: CellArgs,
    # outputs
    cell_key: wp.array(dtype=wp.int32),
    cell_slot: wp.array(dtype=wp.int32),
):
    """Key of each slot: the linear index of its cell (dead: n_cells, sorted last); value: the slot."""
    k = wp.tid()
    n_cells = args.shape[0] * args.shape[1] * args.shape[2]
    key = n_cells
    if args.particle_alive[k] != 0:
        x = args.particle_x[k]
        c = wp.vec3i(0, 0, 0)
        for a in range(3):
            s = int(wp.floor((x[a] - args.origin[a]) / args.cell_size[a]))
            if args.periodic != 0:
                s = s % args.shape[a]
                if s < 0:
                    s += args.shape[a]
            c[a] = wp.clamp(s, 0, args.shape[a] - 1)
        key = (c[0] * args.shape[1] + c[1]) * args.shape[2] + c[2]
    cell_key[k] = key
    cell_slot[k] = k


@wp.kernel
def cell_ranges(
    args: CellArgs,
    n: wp.int32,
    # outputs
    cell_start: wp.array(dtype=wp.int32),
    cell_end: wp.array(dtype=wp.int32),
):
    """[start, end) of every occupied cell from the sorted keys (cells were zeroed: empty cells stay 0, 0)."""
    k = wp.tid()
    key = args.cell_key[k]
    n_cells = args.shape[0] * args.shape[1] * args.shape[2]
    if key >= n_cells:
        return
    if k == 0:
        cell_start[key] = k
    elif args.cell_key[k - 1] != key:
        cell_start[key] = k
    if k == n - 1:
        cell_end[key] = k + 1
    elif args.cell_key[k + 1] != key:
        cell_end[key] = k + 1


@wp.func
def partial_impulse_deficit(impulse_sq: float, mass: float, weight: float, w_min: float):
    """Energy a parcel of ``weight`` particles of ``mass`` loses by taking the impulse w_min J of w_min real
    collisions as one body (dv = w_min J / (weight mass)) instead of w_min of its particles taking J each:
    w_min |J|^2 / (2 mass) - (w_min |J|)^2 / (2 weight mass) = w_min (1 - w_min / weight) |J|^2 / (2 mass), J."""
    return w_min * (1.0 - w_min / weight) * impulse_sq / (2.0 * mass)


@wp.func
def pair_contact_velocities(args: CellArgs, i: int, j: int, n: wp.vec3, particle_v: wp.array(dtype=wp.vec3)):
    """The velocities the model is asked at: the parcels' (spinless), or their contact points' (``args.spin``)."""
    vi = particle_v[i]
    vj = particle_v[j]
    if args.spin != 0:
        vi = contact_point_velocity(vi, args.particle_omega[i], args.particle_radius[i], n)
        vj = contact_point_velocity(vj, args.particle_omega[j], args.particle_radius[j], -n)
    return vi, vj


@wp.func
def write_pair_features(args: CellArgs, i: int, j: int, n: wp.vec3, particle_v: wp.array(dtype=wp.vec3), row: int,
                        features: wp.array2d(dtype=wp.float32)) -> int:
    """The model's features of the pair at the (contact points') velocities into ``features[row]``; 1 if clamped."""
    ci, cj = pair_contact_velocities(args, i, j, n, particle_v)
    di = 2.0 * args.particle_radius[i]
    dj = 2.0 * args.particle_radius[j]
    if args.spin_form != 0:
        return write_contact_spin_features_in_domain(particle_v[i], particle_v[j], ci, cj, n, di, dj,
                                                     args.particle_density[i], args.particle_density[j], args.domain,
                                                     row, features)
    return write_contact_features_in_domain(ci, cj, n, di, dj, args.particle_density[i], args.particle_density[j],
                                            args.domain, row, features)


TRANSFER_SCALE_MAX = wp.constant(4.0)
"""Largest c of ``transfer_scale`` (a post-collision normal separation speed below a quarter of J_n / mu, e < 1/3)."""


@wp.func
def transfer_scale(J: wp.vec3, n: wp.vec3, vi: wp.vec3, vj: wp.vec3, mi: float, mj: float):
    """c of the collisional transfer (Enskog's collisional momentum flux; the consistent Boltzmann algorithm's
    displacement, Alexander, Garcia & Alder 1995): a real pair of contact distance d that exchanges J (on j) passes
    the momentum d J.n across the contact (the collision virial). Point particles that move apart along n by
    c d m_j / (m_i + m_j) (i) and c d m_i / (m_i + m_j) (j) after the collision carry their new momenta
    across c d mu g'_n of it, g'_n = (v_j' - v_i').n the real pair's normal separation speed (vi, vj the velocities
    before): c = J.n / (mu g'_n) makes the two equal, (1 + e) / e for smooth spheres (2 elastic). Clamped to
    [0, TRANSFER_SCALE_MAX]."""
    mu = mi * mj / (mi + mj)
    jn = wp.dot(J, n)
    gn = wp.dot(vj + J / mj - vi + J / mi, n)
    if jn <= 0.0:
        return 0.0
    if gn * TRANSFER_SCALE_MAX <= jn / mu:
        return TRANSFER_SCALE_MAX
    return jn / (mu * gn)


@wp.func
def collisional_displacement(d: float, m_self: float, m_other: float, w_self: float, w_min: float, c: float):
    """How far one parcel's centre moves along its side of the normal after an event (``transfer_scale``): a real
    particle moves c d m_other / (m_self + m_other), and w_min of the parcel's w_self particles did so:
    c d m_other / (m_self + m_other) w_min / w_self, m. The parcels' mass-weighted centre, sum w m x, stays."""
    return c * d * m_other / (m_self + m_other) * (w_min / w_self)


@wp.func
def resolve_pair(args: CellArgs, i: int, j: int, n: wp.vec3, impulse_n: float, impulse_t: float, impulse_b: float,
                 moment_t: float, moment_b: float, particle_v: wp.array(dtype=wp.vec3)):
    """The forest's normalised impulse for parcels i, j along n (approaching) through the guard, applied as the
    weighted equal and opposite impulse into particle_v; returns the guard flags."""
    vi = particle_v[i]
    vj = particle_v[j]
    ri = args.particle_radius[i]
    rj = args.particle_radius[j]
    ci, cj = pair_contact_velocities(args, i, j, n, particle_v)
    g = ci - cj
    cos_angle = wp.dot(g, n) / wp.length(g)
    flags = int(0)
    mi = sphere_mass(2.0 * ri, args.particle_density[i])
    mj = sphere_mass(2.0 * rj, args.particle_density[j])
    J = wp.vec3(0.0)
    if args.spin != 0 or args.spin_form != 0:
        impulse_n, impulse_t, impulse_b, flags = spin_guard(cos_angle, impulse_n, impulse_t, impulse_b,
                                                            args.domain.friction_bound, args.domain.separation_slack,
                                                            args.spin)
        J = contact_spin_impulse(vi, vj, ci, cj, n, mi, mj, impulse_n, impulse_t, impulse_b)  # on j; i gets -J
    else:
        impulse_n, impulse_t, flags = admissible_impulse(cos_angle, impulse_n, impulse_t, args.domain.friction_bound,
                                                         args.domain.separation_slack)
        J = contact_impulse(ci, cj, n, mi, mj, impulse_n, impulse_t)  # on j; i gets -J
    wi = args.particle_weight[i]
    wj = args.particle_weight[j]
    w_min = wp.min(wi, wj)
    particle_v[i] = vi - J * (w_min / (wi * mi))
    particle_v[j] = vj + J * (w_min / (wj * mj))
    if args.transfer != 0:  # the Enskog collisional transfer: the pair moves apart along n (i behind, j ahead)
        d = ri + rj
        c = transfer_scale(J, n, vi, vj, mi, mj)
        args.particle_x[i] = args.particle_x[i] - n * collisional_displacement(d, mi, mj, wi, w_min, c)
        args.particle_x[j] = args.particle_x[j] + n * collisional_displacement(d, mj, mi, wj, w_min, c)
    if args.spin != 0:
        J_rot = J
        if args.spin_form != 0:
            J_rot = contact_spin_impulse(vi, vj, ci, cj, n, mi, mj, 0.0, moment_t, moment_b)
        wi_new, wj_new, fell_back = turn_spins(vi, vj, particle_v[i], particle_v[j], args.particle_omega[i],
                                               args.particle_omega[j], n, ri, rj, mi, mj, wi, wj, w_min / wi,
                                               w_min / wj, J, J_rot)
        args.particle_omega[i] = wi_new
        args.particle_omega[j] = wj_new
        if fell_back != 0:
            flags = flags | GUARD_ENERGY
            J_rot = J
        # the heavier parcel's spin spread: w_min (1 - w_min/w) I |d omega_1|^2 / 2 (d omega_1 of one real collision)
        # as a tensor along the kick (trace: the energy), as the translational deficit below
        if wi > w_min:
            ki = spin_kick(J_rot, n, ri, mi)
            lost = w_min * (1.0 - w_min / wi) * 0.2 * mi * ri * ri * wp.outer(ki, ki)
            args.particle_spin_deficit[i] = args.particle_spin_deficit[i] + lost
        if wj > w_min:
            kj = spin_kick(J_rot, n, rj, mj)
            lost = w_min * (1.0 - w_min / wj) * 0.2 * mj * rj * rj * wp.outer(kj, kj)
            args.particle_spin_deficit[j] = args.particle_spin_deficit[j] + lost
    # the heavier parcel's energy deficit against w_min real collisions (module docstring; none for equal weights)
    j2 = wp.dot(J, J)
    along = wp.mat33(0.0)  # the spread's direction: J J^T / |J|^2
    if j2 > 0.0:
        along = wp.outer(J, J) / j2
    if wi > w_min:
        args.particle_deficit[i] = args.particle_deficit[i] + partial_impulse_deficit(j2, mi, wi, w_min) * along
    if wj > w_min:
        args.particle_deficit[j] = args.particle_deficit[j] + partial_impulse_deficit(j2, mj, wj, w_min) * along
    return flags


@wp.func
def count_guard(args: CellArgs, flags: int):
    if (flags & GUARD_SEPARATION) != 0:
        wp.atomic_add(args.counts, COUNT_SEPARATION, 1)
    if (flags & GUARD_COULOMB) != 0:
        wp.atomic_add(args.counts, COUNT_COULOMB, 1)
    if (flags & GUARD_ENERGY) != 0:
        wp.atomic_add(args.counts, COUNT_ENERGY, 1)


@wp.func
def remember_partner(args: CellArgs, i: int, j: int):
    """Put j first in i's recent partners (moved up if already there, the oldest dropped)."""
    r = args.recent_partners.shape[1]
    k = r - 1
    for m in range(r - 1):  # where j already is, else the last slot
        if args.recent_partners[i, m] == j and k == r - 1:
            k = m
    while k > 0:
        args.recent_partners[i, k] = args.recent_partners[i, k - 1]
        k -= 1
    args.recent_partners[i, 0] = j


@wp.func
def cell_offset(args: CellArgs, i: int, j: int):
    """x_j - x_i, the nearest image in a periodic box (a shifted lattice's cell may straddle the box's side)."""
    dx = args.particle_x[j] - args.particle_x[i]
    if args.periodic != 0:
        for ax in range(3):
            side = args.cell_size[ax] * float(args.shape[ax])
            dx[ax] = dx[ax] - side * wp.round(dx[ax] / side)
    return dx


@wp.kernel
def cell_prepare(
    args: CellArgs,
    particle_v: wp.array(dtype=wp.vec3),
):
    """One collision cell: its majorant, real solids volume, candidate count and random state for the step."""
    cell = wp.tid()
    args.cell_remaining[cell] = 0
    args.pending_row[cell] = -1
    start = args.cell_start[cell]
    end = args.cell_end[cell]
    count = end - start
    if count < 2:
        return
    # the cell's majorant: largest radius and weight, real solids volume, mean velocity, largest |v - c|
    r_max = float(0.0)
    w_max = float(0.0)
    solids = float(0.0)
    e_max = float(0.0)  # local_density: the largest parcel_eps_local and own share w V_p of the cell
    wv_max = float(0.0)
    c = wp.vec3(0.0)
    for k in range(start, end):
        p = args.cell_slot[k]
        r = args.particle_radius[p]
        w = args.particle_weight[p]
        r_max = wp.max(r_max, r)
        w_max = wp.max(w_max, w)
        solids += w * sphere_volume(r)
        if args.local_density != 0:
            e_max = wp.max(e_max, args.particle_eps_local[p])
            wv_max = wp.max(wv_max, w * sphere_volume(r))
        c += particle_v[p]
    c = c / float(count)
    u_max = float(0.0)
    for k in range(start, end):
        u_max = wp.max(u_max, wp.length(particle_v[args.cell_slot[k]] - c))
    volume = cell_volume_of(args, cell)
    chi_max = float(1.0)
    if args.local_density != 0:
        chi_max = local_factor(e_max, (solids - wv_max) / volume, args.enskog, args.eps_cap)
    elif args.enskog != 0:
        chi_max = carnahan_starling(solids / volume, args.eps_cap)
    sigma_g_max = wp.pi * (2.0 * r_max) * (2.0 * r_max) * (2.0 * u_max)
    if args.approaching != 0 and args.approach_redraw == 0:  # approaching pairs at twice the rate: twice the majorant
        sigma_g_max = 2.0 * sigma_g_max
    args.cell_sigma_g_max[cell] = sigma_g_max
    pairs = float(count) * float(count - 1)
    if args.transfer != 0:
        # the displacements give the parcels the hard-sphere gas's structure (the consistent Boltzmann algorithm
        # reproduces its equation of state), so counts vary as S N, not N: E[N (N - 1)] = n^2 V^2 - (1 - S) k n V,
        # and N (N - 1) + (1 - S) k N counts the pairs of the mean density without bias. k: a finite cell keeps less
        # of the pair correlation than S(0) counts, the excluded-volume hole (radius d) of a parcel near a face
        # reaching out of the cell; of the pair displacements r within d, a box of edges L_a keeps on average
        # prod (1 - |r_a| / L_a) ~ 1 - (3/8) d sum 1 / L_a (<|r_a|> = 3 d / 8 over the ball). At weight 1 (16 parcels
        # per cell), eps_s = 0.05, the homogeneous gas collides 0.998-1.006 times Enskog's frequency with k,
        # 1.003-1.011 with k = 1, 0.981-0.990 with neither; with 4 parcels per cell it over-counts, +2 % at weight
        # 1 and +5 % at weight 64 (cases/homogeneous_cooling.py)
        d_max = 2.0 * r_max
        kept = 1.0 - 0.375 * d_max * (1.0 / args.cell_size[0] + 1.0 / args.cell_size[1] + 1.0 / args.cell_size[2])
        pairs += (1.0 - compressibility(solids / volume, args.eps_cap)) * wp.max(kept, 0.0) * float(count)
    expected = 0.5 * pairs * w_max * chi_max * sigma_g_max * args.sub_dt[0] / volume
    args.cell_candidates[cell] = expected
    state = wp.rand_init(args.sub_seed[0], cell)
    n_candidates = int(wp.floor(expected))
    if wp.randf(state) < expected - float(n_candidates):
        n_candidates += 1
    args.cell_rng[cell] = state
    args.cell_remaining[cell] = n_candidates
    args.cell_bound[cell] = sigma_g_max * w_max * chi_max
    args.cell_solids[cell] = solids
    wp.atomic_add(args.counts, COUNT_CANDIDATES, n_candidates)
    wp.atomic_add(args.counts, COUNT_CELLS, 1)


@wp.func
def uniform_position(count: int, exclude: int, state: wp.uint32):
    """A position in the cell's [0, count) drawn uniformly, ``exclude`` >= 0 left out (the second parcel of a
    pair); returns (position, state)."""
    k = int(0)
    if exclude < 0:
        k = wp.min(int(wp.randf(state) * float(count)), count - 1)
    else:
        k = wp.min(int(wp.randf(state) * float(count - 1)), count - 2)
        if k >= exclude:
            k += 1
    return k, state


@wp.func
def nearest_partner(args: CellArgs, start: int, count: int, a: int, state: wp.uint32):
    """Position in the cell of the parcel nearest to the cell's ``a``-th, among all the others or ``args.nearest``
    drawn ones, the last partner of ``a`` left out unless it is the only other parcel; returns (position, state)."""
    i = args.cell_slot[start + a]
    last = args.recent_partners[i, 0]
    best = int(-1)
    best_d2 = float(0.0)
    scan_all = count - 1 <= args.nearest
    tries = count
    if not scan_all:
        tries = args.nearest
    for t in range(tries):
        k = t
        if not scan_all:
            k, state = uniform_position(count, a, state)
        if k != a:
            p = args.cell_slot[start + k]
            if p != last:
                d2 = wp.length_sq(cell_offset(args, i, p))
                if best < 0 or d2 < best_d2:
                    best = k
                    best_d2 = d2
    if best < 0:  # only the last partner is left
        best, state = uniform_position(count, a, state)
    return best, state


@wp.func
def draw_of_weight(args: CellArgs, start: int, count: int, w: float, exclude: int, state: wp.uint32):
    """Position in the cell of a parcel of weight ``w`` drawn uniformly among those of the cell (``exclude`` >= 0:
    that position left out), by rejection from uniform draws: the first draw is NTC's (uniform over the cell, or
    over the others when ``exclude`` >= 0), so a cell of one weight consumes the same random numbers as a plain
    draw. At most ``REDRAW_CLASS_TRIES`` x ``count`` draws (a class of one parcel in the cell is missed with
    probability e^-8); returns (position or -1, state)."""
    found = int(-1)
    tries = int(0)
    while found < 0 and tries < REDRAW_CLASS_TRIES * count:
        tries += 1
        k, state = uniform_position(count, exclude, state)
        if args.particle_weight[args.cell_slot[start + k]] == w:
            found = k
    return found, state


@wp.func
def same_weights(args: CellArgs, i0: int, j0: int, wi: float, wj: float):
    """Whether weights wi, wj are those of parcels i0, j0, in either order."""
    a = args.particle_weight[i0]
    b = args.particle_weight[j0]
    return (wi == a and wj == b) or (wi == b and wj == a)


@wp.kernel
def cell_select(
    args_store: wp.array(dtype=CellArgs),
    cell_remaining: wp.array(dtype=wp.int32),
    forest: Forest,
    # outputs
    particle_v: wp.array(dtype=wp.vec3),
    more: wp.array(dtype=wp.int32),
):
    """The cell's candidates in order: selection, acceptance, sampled normal. ``args.batched`` = 1: stop at the
    next accepted pair, write its features into a batch row (resolved by ``cell_apply`` after the batched forest
    evaluation; ``more[0]`` = 1); 0: resolve every accepted pair at once with inline tree walks. ``args_store[0]``:
    the ``CellArgs``, read by the cells with candidates only (``cell_remaining``: ``args.cell_remaining``; a struct
    kernel argument is copied by every CPU thread, and most cells have none)."""
    cell = wp.tid()
    remaining = cell_remaining[cell]
    if remaining <= 0:
        return
    args = args_store[0]
    start = args.cell_start[cell]
    count = args.cell_end[cell] - start
    state = args.cell_rng[cell]
    bound = args.cell_bound[cell]
    solids = args.cell_solids[cell]
    volume = cell_volume_of(args, cell)
    while remaining > 0:
        remaining -= 1
        # The candidate pair is drawn and tested as Bird's NTC. With the approach filter's transfer
        # (approach_redraw > 0), an accepted pair whose centres do not approach hands its collision to another
        # pair of the cell with the same two weights, drawn until one approaches and passes its own acceptance
        # test (at most approach_redraw draws): the cell collides as often as plain NTC, among approaching pairs
        # in proportion to their rates.
        attempt = int(0)
        found = bool(False)
        searching = bool(True)
        i = int(0)
        j = int(0)
        u_b2 = float(0.0)
        u_phi = float(0.0)
        g = wp.vec3(0.0)
        wi = float(0.0)
        wj = float(0.0)
        # an accepted receding candidate (its two weights are the kind its collision goes to; the fallback
        # collides it)
        i0 = int(0)
        j0 = int(0)
        u_b20 = float(0.0)
        u_phi0 = float(0.0)
        seen = bool(False)  # a redrawn pair of other weights approached and was accepted
        restricted = bool(False)  # this draw is among the candidate's two weights only
        while searching:
            a = int(0)
            b = int(0)
            drawn = bool(True)
            if not restricted:  # a pair of the cell as NTC draws it
                a, state = uniform_position(count, -1, state)
                if args.nearest > 0 and attempt == 0:
                    b, state = nearest_partner(args, start, count, a, state)
                else:
                    b, state = uniform_position(count, a, state)
            else:  # a pair of the receding candidate's two weights, uniform among those of the cell
                a, state = draw_of_weight(args, start, count, args.particle_weight[i0], -1, state)
                if a >= 0:
                    b, state = draw_of_weight(args, start, count, args.particle_weight[j0], a, state)
                drawn = a >= 0 and b >= 0
                if not drawn:
                    a = 0
                    b = 1
            i = args.cell_slot[start + a]
            j = args.cell_slot[start + b]
            u_accept = wp.randf(state)
            u_b2 = wp.randf(state)
            u_phi = wp.randf(state)
            g = particle_v[i] - particle_v[j]
            g_mag = wp.length(g)
            wi = args.particle_weight[i]
            wj = args.particle_weight[j]
            rate = float(0.0)
            eligible = bool(True)
            if g_mag > 0.0 and bound > 0.0:
                ri = args.particle_radius[i]
                rj = args.particle_radius[j]
                chi = float(1.0)
                if args.local_density != 0:
                    chi = local_factor(0.5 * (args.particle_eps_local[i] + args.particle_eps_local[j]),
                                       (solids - 0.5 * (wi * sphere_volume(ri) + wj * sphere_volume(rj))) / volume,
                                       args.enskog, args.eps_cap)
                elif args.enskog != 0:
                    chi = carnahan_starling((solids - wi * sphere_volume(ri) - wj * sphere_volume(rj)) / volume,
                                            args.eps_cap)
                rate = wp.pi * (ri + rj) * (ri + rj) * g_mag * wp.max(wi, wj) * chi
                if args.approaching != 0 and (args.approach_redraw == 0 or wp.max(wi, wj) > 1.0):
                    # (the transfer tests pairs with a weighted parcel only: the approach of two single particles
                    # at the cell's scale reads the correlation their own collisions leave, not the flow)
                    dx = cell_offset(args, i, j)
                    # a parcel of w particles is a cloud: its w - 1 other particles fill (w - 1) V_p / eps_cell
                    # around the centre; the colliding particle of each is drawn uniformly from a cube of that
                    # volume (0 at weight 1)
                    u_i = wp.vec3(wp.randf(state) - 0.5, wp.randf(state) - 0.5, wp.randf(state) - 0.5)
                    u_j = wp.vec3(wp.randf(state) - 0.5, wp.randf(state) - 0.5, wp.randf(state) - 0.5)
                    if solids > 0.0:
                        spread_i = wp.pow((wi - 1.0) * sphere_volume(ri) * volume / solids, 1.0 / 3.0)
                        spread_j = wp.pow((wj - 1.0) * sphere_volume(rj) * volume / solids, 1.0 / 3.0)
                        dx = dx + spread_j * u_j - spread_i * u_i
                    met = bool(False)
                    for k in range(args.recent_partners.shape[1]):
                        if args.recent_partners[i, k] == j or args.recent_partners[j, k] == i:
                            met = True
                    if met and wp.max(wi, wj) > 1.0:
                        # a parcel that met this weighted partner: its next real collision is with another
                        # particle of the cloud, not the receding one, which approaches as a random particle of the
                        # cloud does, one time in two (always eligible, the redraw gave met pairs twice their NTC
                        # rate: a single particle met the same weight-8 parcel again 2.2x as often as plain NTC's;
                        # a weight-1 pair that collided stays filtered: it recedes)
                        eligible = wp.randf(state) < 0.5
                    else:
                        eligible = wp.dot(dx, g) > 0.0
                        if args.approach_redraw == 0:  # the doubled-rate rule
                            if eligible:
                                rate = 2.0 * rate
                            else:
                                rate = 0.0
            if rate > bound:
                wp.atomic_add(args.counts, COUNT_OVER_MAX, 1)
            accept = u_accept * bound < rate
            if args.approaching == 0 or args.approach_redraw == 0:
                found = accept
                searching = False
            elif attempt == 0:
                if accept and eligible:
                    found = True
                    searching = False
                elif not accept:  # the NTC candidate itself is rejected
                    searching = False
                else:  # accepted, receding: its collision goes to an approaching pair of the same weights
                    i0 = i
                    j0 = j
                    u_b20 = u_b2
                    u_phi0 = u_phi
                    attempt = 1
            elif not restricted and not same_weights(args, i0, j0, wi, wj):
                # a pair of other weights tells whether the cell's pairs approach at all; a pair of the
                # candidate's weights is then drawn among those (one weight-8 parcel among sixteen single
                # particles finds its partners as often as a common kind)
                if eligible and accept:
                    seen = True
                restricted = True
            elif drawn and accept and eligible:
                found = True
                searching = False
            else:
                restricted = False
                attempt += 1
                if attempt > args.approach_redraw:
                    searching = False
                    if seen:  # other kinds found partners, this rare one none: the candidate collides itself
                        i = i0
                        j = j0
                        g = particle_v[i] - particle_v[j]  # no velocity changes within a candidate's draws
                        u_b2 = u_b20
                        u_phi = u_phi0
                        wi = args.particle_weight[i]
                        wj = args.particle_weight[j]
                        found = True
                    # else: no pair of the cell approaches (two streams that have passed): lost
        if not found:
            continue
        wp.atomic_add(args.counts, COUNT_ACCEPTED, 1)
        if args.approaching != 0 or args.nearest > 0:  # only these read the memory
            remember_partner(args, i, j)
            remember_partner(args, j, i)
        n = sample_normal(g, u_b2, u_phi)
        if args.log_pair.shape[0] > 0:
            slot = wp.atomic_add(args.log_count, 0, 1)
            if slot < args.log_pair.shape[0]:
                args.log_pair[slot] = wp.vec2i(i, j)
                args.log_g[slot] = g
                args.log_normal[slot] = n
            else:
                wp.atomic_add(args.counts, COUNT_LOG_OVERFLOW, 1)
        s = stream_pair_index(args.particle_stream[i], args.particle_stream[j], args.n_streams)
        wp.atomic_add(args.calls, s, 1)
        wp.atomic_add(args.collisions, s, wp.int32(wp.min(wi, wj) + 0.5))
        if args.apply == 0:
            continue
        if args.batched != 0:
            row = wp.atomic_add(args.batch_count, 0, 1)
            if write_pair_features(args, i, j, n, particle_v, row, args.batch_features) == 1:
                wp.atomic_add(args.counts, COUNT_CLAMPED, 1)
            args.pending_row[cell] = row
            args.pending_pair[cell] = wp.vec2i(i, j)
            args.pending_normal[cell] = n
            more[0] = 1
            break
        if write_pair_features(args, i, j, n, particle_v, cell, args.features) == 1:
            wp.atomic_add(args.counts, COUNT_CLAMPED, 1)
        impulse_b = float(0.0)
        moment_t = float(0.0)
        moment_b = float(0.0)
        if args.spin_form != 0:
            impulse_b = forest_target(forest, 2, args.features, cell)
            if args.spin != 0:
                moment_t = forest_target(forest, 3, args.features, cell)
                moment_b = forest_target(forest, 4, args.features, cell)
        flags = resolve_pair(args, i, j, n, forest_target(forest, 0, args.features, cell),
                             forest_target(forest, 1, args.features, cell), impulse_b, moment_t, moment_b, particle_v)
        count_guard(args, flags)
    args.cell_remaining[cell] = remaining
    args.cell_rng[cell] = state


@wp.kernel
def cell_apply(
    args_store: wp.array(dtype=CellArgs),
    pending_row: wp.array(dtype=wp.int32),
    # outputs
    particle_v: wp.array(dtype=wp.vec3),
):
    """The batched round's outcome of each cell's pending pair (``batch_out`` row), guarded and applied
    (``args_store[0]``: the ``CellArgs``, read by the cells with a pending pair only; ``pending_row``:
    ``args.pending_row``)."""
    cell = wp.tid()
    row = pending_row[cell]
    if row < 0:
        return
    args = args_store[0]
    pair = args.pending_pair[cell]
    impulse_b = float(0.0)
    moment_t = float(0.0)
    moment_b = float(0.0)
    if args.spin_form != 0:
        impulse_b = args.batch_out[row, 2]
        moment_t = args.batch_out[row, 3]
        moment_b = args.batch_out[row, 4]
    flags = resolve_pair(args, pair[0], pair[1], args.pending_normal[cell], args.batch_out[row, 0],
                         args.batch_out[row, 1], impulse_b, moment_t, moment_b, particle_v)
    count_guard(args, flags)
    args.pending_row[cell] = -1


@wp.kernel
def store_cell_args(
    args: CellArgs,
    # outputs
    args_store: wp.array(dtype=CellArgs),
):
    """args_store[0] = args (``cell_select``, ``cell_apply``)."""
    args_store[0] = args


@wp.kernel
def path_advance(
    particle_v: wp.array(dtype=wp.vec3),
    particle_alive: wp.array(dtype=wp.int32),
    sub_dt: wp.array(dtype=wp.float32),
    # outputs
    path_x: wp.array(dtype=wp.vec3),
):
    """A sub-step along the straight path with the velocity after the sub-step's collisions: x += v dt."""
    i = wp.tid()
    if particle_alive[i] != 0:
        path_x[i] = path_x[i] + particle_v[i] * sub_dt[0]


# ------------------------------------------------------------------------------------------ the sub-step loop
# The step's sub-steps are planned and counted on the device: K from the live parcels' largest speed (the
# ``live_extremes`` array) and, with the approach filter, from the last step's accepted events per parcel, so that
# the loop can run as a graph's while node without reading K back (``HelConfig.read_back`` 'output'); the host loop
# takes the same K, dt and seeds from here.
LOOP_K, LOOP_SUBSTEPS, LOOP_SEED = 0, 1, 2
"""Slots of the (3,) int32 loop state: sub-step index, sub-steps of the step, the step's seed."""


@wp.func
def mix_seed(seed: wp.int32, step: wp.int32) -> wp.int32:
    """``hel_warp.collisions.cells.step_seed`` on the device: splitmix64 of the pair, 31 bits."""
    z = wp.uint64(seed) * wp.uint64(0x9E3779B97F4A7C15) + wp.uint64(step) + wp.uint64(0x632BE59BD9B4E019)
    z = (z ^ (z >> wp.uint64(30))) * wp.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> wp.uint64(27))) * wp.uint64(0x94D049BB133111EB)
    return wp.int32((z ^ (z >> wp.uint64(31))) & wp.uint64(0x7FFFFFFF))


@wp.kernel
def substep_plan(
    extremes: wp.array(dtype=wp.float64),
    events: wp.array(dtype=wp.float64),
    dt: wp.float64,
    path_cell: wp.float64,
    max_substeps: int,
    approaching: int,
    approach_events: wp.float64,
    host_substeps: int,
    step_seed: int,
    # outputs
    loop: wp.array(dtype=wp.int32),
    more: wp.array(dtype=wp.int32),
    sub_dt: wp.array(dtype=wp.float32),
):
    """K = ceil(v_max dt / (cfl h_min)), with ``approaching`` at least ceil(events per parcel / approach_events),
    within [1, max_substeps] (the host's float64 arithmetic, so the same K); ``host_substeps`` > 0: that K (the
    host loop's). The loop state starts at sub-step 0 and dt / K is the sub-step."""
    k = host_substeps
    if k <= 0:
        paths = extremes[0] * dt / path_cell
        k = max_substeps
        if paths < wp.float64(max_substeps):  # NaN and inf keep the largest
            k = wp.max(1, int(wp.ceil(paths)))
        if approaching != 0:
            need = events[0] / approach_events - wp.float64(1.0e-9)
            if need < wp.float64(max_substeps):
                k = wp.max(k, int(wp.ceil(need)))
            else:
                k = max_substeps
        k = wp.min(k, max_substeps)
    loop[LOOP_K] = 0
    loop[LOOP_SUBSTEPS] = k
    loop[LOOP_SEED] = step_seed
    more[0] = 1
    sub_dt[0] = wp.float32(dt / wp.float64(k))


@wp.kernel
def substep_begin(loop: wp.array(dtype=wp.int32), sub_seed: wp.array(dtype=wp.int32)):
    """The sub-step's seed from the step's and the sub-step index."""
    sub_seed[0] = mix_seed(loop[LOOP_SEED], loop[LOOP_K])


@wp.kernel
def substep_end(loop: wp.array(dtype=wp.int32), more: wp.array(dtype=wp.int32)):
    """The next sub-step; ``more`` 0 after the last."""
    k = loop[LOOP_K] + 1
    loop[LOOP_K] = k
    if k < loop[LOOP_SUBSTEPS]:
        more[0] = 1
    else:
        more[0] = 0


@wp.kernel
def substep_events(counts: wp.array(dtype=wp.int32), extremes: wp.array(dtype=wp.float64),
                   events: wp.array(dtype=wp.float64)):
    """Accepted events per live parcel of the step (each counted for both parcels): the next step's plan."""
    events[0] = wp.float64(2.0) * wp.float64(counts[COUNT_ACCEPTED]) / wp.float64(wp.max(int(extremes[3]), 1))


@wp.kernel
def path_shift(
    path_x: wp.array(dtype=wp.vec3),
    particle_x: wp.array(dtype=wp.vec3),
    particle_v: wp.array(dtype=wp.vec3),
    particle_alive: wp.array(dtype=wp.int32),
    dt: float,
    # outputs
    shift: wp.array(dtype=wp.vec3),
):
    """The in-step position change the push will not make: end of the sub-stepped path minus x + v_final dt."""
    i = wp.tid()
    shift[i] = wp.vec3(0.0)
    if particle_alive[i] != 0:
        shift[i] = path_x[i] - (particle_x[i] + particle_v[i] * dt)


@wp.kernel
def cell_next_round(
    max_rounds: int,
    min_rows: int,
    batch_count: wp.array(dtype=wp.int32),
    # outputs
    more: wp.array(dtype=wp.int32),
    round_count: wp.array(dtype=wp.int32),
    rounds_total: wp.array(dtype=wp.int32),
):
    """Counts the batched round; stops the rounds at ``max_rounds`` or after a round of fewer than ``min_rows`` pairs
    (a batched evaluation costs a block of rows however few are used; the rest is resolved inline)."""
    r = round_count[0] + 1
    round_count[0] = r
    rounds_total[0] = rounds_total[0] + 1
    if r >= max_rounds or batch_count[0] < min_rows:
        more[0] = 0


@wp.func
def block_cell(args: CellArgs, lo: wp.vec3i, hi: wp.vec3i, k: int):
    """Linear index of the k-th cell of the block [lo, hi) (x slowest, as ``cell_keys``)."""
    ny = hi[1] - lo[1]
    nz = hi[2] - lo[2]
    cx = lo[0] + k // (ny * nz)
    cy = lo[1] + (k // nz) % ny
    cz = lo[2] + k % nz
    return (cx * args.shape[1] + cy) * args.shape[2] + cz


@wp.func
def as_vec3d(v: wp.vec3):
    return wp.vec3d(wp.float64(v[0]), wp.float64(v[1]), wp.float64(v[2]))


@wp.func
def tensor_kick(tensor: wp.mat33, xi: wp.vec3d):
    """A random vector of covariance ``tensor`` (symmetric, >= 0; tiny negative eigenvalues of round-off taken as
    0): along each eigenvector, sqrt(lambda) times a component of ``xi`` (three standard normals)."""
    axes, energies = wp.eig3(tensor)
    kick = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    for a in range(3):
        e = wp.float64(wp.max(energies[a], 0.0))
        axis = wp.vec3d(wp.float64(axes[0, a]), wp.float64(axes[1, a]), wp.float64(axes[2, a]))
        kick += wp.sqrt(e) * xi[a] * axis
    return kick


@wp.func
def exact_energy_scale(energy: wp.float64, deficit: wp.float64, cross: wp.float64):
    """alpha of the restorations: after a kick of its own energy ``deficit`` whose cross term with the velocities is
    ``cross``, scaling the (peculiar) velocities of ``energy`` by alpha leaves exactly energy + deficit:
    alpha^2 = (energy + deficit) / (energy + deficit + cross) (1 where the kicked energy is 0)."""
    after = energy + deficit + cross
    alpha = wp.float64(1.0)
    if after > wp.float64(0.0):
        alpha = wp.sqrt((energy + deficit) / after)
    return alpha


@wp.func
def deficit_kick(args: CellArgs, p: int, mass: wp.float64, xi: wp.vec3d):
    """The parcel's random kick (its lost spread), covariance 2 T / mass for its deficit tensor T
    (``tensor_kick``; ``xi`` three standard normals, drawn by the caller whether the deficit is 0 or not, so that
    both passes replay the same numbers); expected energy trace T, m/s."""
    return wp.sqrt(wp.float64(2.0) / mass) * tensor_kick(args.particle_deficit[p], xi)


@wp.func
def restore_class(args: CellArgs, lo: wp.vec3i, hi: wp.vec3i, weight: float, key: int,
                  particle_v: wp.array(dtype=wp.vec3)):
    """The block's parcels of ``weight``: their deficits D put back as the random spread they are. Each parcel gets
    a kick s delta_k, delta_k its ``deficit_kick`` (along its impulses) less the class's mass-weighted
    mean kick (momentum exact), s = sqrt(2 D / sum M_k |delta_k|^2) (the kicks' own energy exactly D); the class's
    velocities about its mass-weighted mean u are then scaled by the alpha that makes the energy gained exactly D:
    v_k' = u + alpha (v_k - u + s delta_k), alpha^2 = (P + D) / (P + D + R), P the class's energy about u before,
    R = s sum M_k (v_k - u).delta_k the kicks' cross term (zero in expectation, so alpha ~ 1; P + D + R >= 0 always).
    One pass gathers the sums (the centred ones from the raw: sum M |delta|^2 = sum M |k|^2 - M |k_mean|^2, and so
    on, in float64), a second applies the kicks. Deficits zeroed. The random numbers come from
    ``wp.rand_init(key)``, replayed in each pass. Returns 1 when restored, 0 when the class cannot take it (one
    parcel in the block: no momentum partner)."""
    n_block = (hi[0] - lo[0]) * (hi[1] - lo[1]) * (hi[2] - lo[2])
    zero = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    mass = wp.float64(0.0)
    kick_momentum = zero
    momentum = zero
    kick_square = wp.float64(0.0)  # sum M |k|^2
    velocity_kick = wp.float64(0.0)  # sum M v.k
    velocity_square = wp.float64(0.0)  # sum M |v|^2
    deficit = wp.float64(0.0)
    members = int(0)
    state = wp.rand_init(key)
    for k in range(n_block):
        cell = block_cell(args, lo, hi, k)
        for s in range(args.cell_start[cell], args.cell_end[cell]):
            p = args.cell_slot[s]
            if args.particle_weight[p] == weight:
                m = wp.float64(weight * sphere_mass(2.0 * args.particle_radius[p], args.particle_density[p]))
                xi = wp.vec3d(wp.float64(wp.randn(state)), wp.float64(wp.randn(state)), wp.float64(wp.randn(state)))
                kick = deficit_kick(args, p, m, xi)
                v = as_vec3d(particle_v[p])
                mass += m
                kick_momentum += m * kick
                momentum += m * v
                kick_square += m * wp.dot(kick, kick)
                velocity_kick += m * wp.dot(v, kick)
                velocity_square += m * wp.dot(v, v)
                deficit += wp.float64(wp.trace(args.particle_deficit[p]))
                members += 1
    mean_kick = kick_momentum / mass
    u = momentum / mass
    quadratic = kick_square - mass * wp.dot(mean_kick, mean_kick)  # sum M |delta|^2
    linear = velocity_kick - mass * wp.dot(u, mean_kick)  # sum M (v - u).delta
    peculiar = wp.float64(0.5) * wp.max(velocity_square - mass * wp.dot(u, u), wp.float64(0.0))  # sum M |v - u|^2 / 2
    restored = int(0)
    scale = wp.float64(0.0)
    alpha = wp.float64(1.0)
    if members >= 2 and quadratic > wp.float64(0.0):
        scale = wp.sqrt(wp.float64(2.0) * deficit / quadratic)
        alpha = exact_energy_scale(peculiar, deficit, scale * linear)
        restored = 1
    state = wp.rand_init(key)
    for k in range(n_block):
        cell = block_cell(args, lo, hi, k)
        for s in range(args.cell_start[cell], args.cell_end[cell]):
            p = args.cell_slot[s]
            if args.particle_weight[p] == weight:
                m = wp.float64(weight * sphere_mass(2.0 * args.particle_radius[p], args.particle_density[p]))
                xi = wp.vec3d(wp.float64(wp.randn(state)), wp.float64(wp.randn(state)), wp.float64(wp.randn(state)))
                delta = deficit_kick(args, p, m, xi) - mean_kick
                args.particle_deficit[p] = wp.mat33(0.0)
                if restored == 1:
                    nv = u + alpha * (as_vec3d(particle_v[p]) - u + scale * delta)
                    particle_v[p] = wp.vec3(wp.float32(nv[0]), wp.float32(nv[1]), wp.float32(nv[2]))
    return restored


@wp.func
def restore_spin(args: CellArgs, p: int, xi: wp.vec3):
    """The parcel's lost spin spread put back: a kick k of covariance 2 T / I_w for its ``particle_spin_deficit``
    tensor T (along the events' one-collision spin changes; ``xi`` three standard normals; I_w = weight 2/5 m r^2),
    scaled by s so that its own energy I_w s^2 |k|^2 / 2 is D = trace T, then omega' = alpha (omega + s k) with
    alpha^2 = (E + D) / (E + D + R), E = I_w |omega|^2 / 2 and R = I_w s omega.k (zero in expectation): exactly D
    more rotational energy, the spin changed by about the deficit's own spread. No partner needed: the collisions'
    moment impulses do not keep the spins' sum either. The deficit zeroed. (Not omega + s xi with the root s of
    I_w (s omega.xi + s^2 |xi|^2 / 2) = D: that mirrors omega about a random plane whenever omega.xi < 0 and D is
    small.)"""
    r = args.particle_radius[p]
    inertia = wp.float64(args.particle_weight[p] * 0.4 * sphere_mass(2.0 * r, args.particle_density[p]) * r * r)
    tensor = args.particle_spin_deficit[p]
    deficit = wp.float64(wp.trace(tensor))
    args.particle_spin_deficit[p] = wp.mat33(0.0)
    k = tensor_kick(tensor, as_vec3d(xi))
    kk = wp.dot(k, k)
    if kk > wp.float64(0.0) and inertia > wp.float64(0.0) and deficit > wp.float64(0.0):
        w = as_vec3d(args.particle_omega[p])
        s = wp.sqrt(wp.float64(2.0) * deficit / (inertia * kk))
        alpha = exact_energy_scale(wp.float64(0.5) * inertia * wp.dot(w, w), deficit, inertia * s * wp.dot(w, k))
        nw = alpha * (w + s * k)
        args.particle_omega[p] = wp.vec3(wp.float32(nw[0]), wp.float32(nw[1]), wp.float32(nw[2]))


@wp.kernel
def cell_restore(
    args: CellArgs,
    block: int,
    # outputs
    particle_v: wp.array(dtype=wp.vec3),
):
    """One block of block^3 collision cells: every weight class with a deficit restored (``restore_class``); the
    block's random stream ``wp.rand_init(seed, n_cells + block index)`` (the cells' streams are 0 .. n_cells-1)."""
    b = wp.tid()
    nb1 = (args.shape[1] + block - 1) // block
    nb2 = (args.shape[2] + block - 1) // block
    lo = wp.vec3i((b // (nb1 * nb2)) * block, ((b // nb2) % nb1) * block, (b % nb2) * block)
    hi = wp.vec3i(wp.min(lo[0] + block, args.shape[0]), wp.min(lo[1] + block, args.shape[1]),
                  wp.min(lo[2] + block, args.shape[2]))
    n_block = (hi[0] - lo[0]) * (hi[1] - lo[1]) * (hi[2] - lo[2])
    block_state = wp.rand_init(args.sub_seed[0], args.shape[0] * args.shape[1] * args.shape[2] + b)
    for k in range(n_block):
        cell = block_cell(args, lo, hi, k)
        for s in range(args.cell_start[cell], args.cell_end[cell]):
            p = args.cell_slot[s]
            if wp.trace(args.particle_deficit[p]) > 0.0:
                key = wp.randi(block_state)
                if restore_class(args, lo, hi, args.particle_weight[p], key, particle_v) == 1:
                    wp.atomic_add(args.counts, COUNT_RESTORED, 1)
                else:
                    wp.atomic_add(args.counts, COUNT_UNRESTORED, 1)
    if args.spin != 0:
        spin_state = wp.rand_init(args.sub_seed[0] + 7919, args.shape[0] * args.shape[1] * args.shape[2] + b)
        for k in range(n_block):
            cell = block_cell(args, lo, hi, k)
            for s in range(args.cell_start[cell], args.cell_end[cell]):
                p = args.cell_slot[s]
                if wp.trace(args.particle_spin_deficit[p]) > 0.0:
                    restore_spin(args, p, wp.vec3(wp.randn(spin_state), wp.randn(spin_state), wp.randn(spin_state)))


# ------------------------------------------------------------------------------------------ launch wrappers


def advance_paths(path_x, particle_v, particle_alive, sub_dt) -> None:
    """x += v dt along the paths, dt the (1,) float32 ``sub_dt``."""
    wp.launch(path_advance, dim=path_x.shape[0], device=path_x.device, inputs=[particle_v, particle_alive, sub_dt],
              outputs=[path_x])


def path_shifts(path_x, particle_x, particle_v, particle_alive, dt: float, shift) -> None:
    wp.launch(path_shift, dim=path_x.shape[0], device=path_x.device,
              inputs=[path_x, particle_x, particle_v, particle_alive, float(dt)], outputs=[shift])



def restore_energy(args: CellArgs, particle_v, block: int) -> None:
    """After a sub-step's collisions (:func:`collide_cells`): the unequal-weight deficits put back per block of
    ``block``^3 cells and weight class (``cell_restore``)."""
    shape = args.shape
    blocks = 1
    for a in range(3):
        blocks *= (int(shape[a]) + block - 1) // block
    wp.launch(cell_restore, dim=blocks, device=particle_v.device, inputs=[args, int(block)], outputs=[particle_v])


def fill_fluid_volumes(args: CellArgs) -> None:
    """``args.cell_fluid_volume`` for the lattice in ``args`` (with ``use_fluid``; after each lattice shift)."""
    if args.use_fluid != 0:
        n_cells = int(args.shape[0]) * int(args.shape[1]) * int(args.shape[2])
        wp.launch(cell_fluid_volumes, dim=n_cells, device=args.cell_fluid_volume.device, inputs=[args])


def sort_by_cell(args: CellArgs) -> None:
    """Per-cell parcel lists: keys, a stable radix sort, then the cell ranges (``args.cell_start`` / ``cell_end``
    are zeroed here)."""
    n = args.particle_x.shape[0]
    device = args.particle_x.device
    wp.launch(cell_keys, dim=n, device=device, inputs=[args], outputs=[args.cell_key, args.cell_slot])
    wp.utils.radix_sort_pairs(args.cell_key, args.cell_slot, n)
    args.cell_start.zero_()
    args.cell_end.zero_()
    wp.launch(cell_ranges, dim=n, device=device, inputs=[args, n], outputs=[args.cell_start, args.cell_end])


def collide_cells(args: CellArgs, forest: Forest, particle_v, more, round_count, rounds_total,
                  batch_forest: Forest | None = None, max_rounds: int = 64, min_rows: int = 32,
                  args_store=None) -> None:
    """Every cell's candidates, acceptance and outcomes (after :func:`sort_by_cell`); counters accumulate (the
    caller zeroes them per step). With ``batch_forest`` (perfect layout): rounds of one accepted pair per cell,
    each round's pairs predicted in one batched evaluation, until no cell has candidates left
    (``wp.capture_while``: a graph loop on CUDA), ``max_rounds`` rounds or a round of fewer than ``min_rows`` pairs,
    the rest inline; else one round of
    inline walks of ``forest`` (explicit layout). ``more``, ``round_count``: (1,) int32 scratch; ``rounds_total``
    (1,) += the batched rounds taken. Both give the same pairs in the same order per cell. ``args_store``: a
    one-element ``CellArgs`` array (allocated if None) from which the cell kernels read ``args``; the rounds'
    launches are recorded once per call and replayed."""
    device = particle_v.device
    n_cells = args.cell_start.shape[0]
    if args_store is None:
        args_store = wp.empty(1, dtype=CellArgs, device=device)
    args.batched = 0 if batch_forest is None else 1
    wp.launch(cell_prepare, dim=n_cells, device=device, inputs=[args, particle_v])

    def select_inline():
        args.batched = 0
        wp.launch(store_cell_args, dim=1, device=device, inputs=[args], outputs=[args_store])
        wp.launch(cell_select, dim=n_cells, device=device, inputs=[args_store, args.cell_remaining, forest],
                  outputs=[particle_v, more])

    if batch_forest is None:
        select_inline()
        return
    from kernels.forest import eval_forest

    wp.launch(store_cell_args, dim=1, device=device, inputs=[args], outputs=[args_store])

    def record(kernel, dim, inputs, outputs):
        return wp.launch(kernel, dim=dim, device=device, inputs=inputs, outputs=outputs, record_cmd=True)

    select = record(cell_select, n_cells, [args_store, args.cell_remaining, forest], [particle_v, more])
    predict = eval_forest(batch_forest, args.batch_features, args.batch_out, device=device,
                          row_count=args.batch_count, record=True)
    apply = record(cell_apply, n_cells, [args_store, args.pending_row], [particle_v])
    next_round = record(cell_next_round, 1, [int(max_rounds), int(min_rows), args.batch_count],
                        [more, round_count, rounds_total])

    def one_round():
        more.zero_()
        args.batch_count.zero_()
        select.launch()
        if predict is not None:
            predict.launch()
        apply.launch()
        next_round.launch()

    more.fill_(1)
    round_count.zero_()
    wp.capture_while(more, one_round)
    # the cells still holding candidates after the rounds (dense cells: one round per accepted pair would take
    # thousands; the last few pairs of a sparse step: a batch of a few rows costs a whole block) finish inline, in
    # the same order
    select_inline()


@wp.kernel
def local_solids_kernel(
    grid: CellGrid,
    particle_x: wp.array(dtype=wp.vec3),
    particle_weight: wp.array(dtype=wp.float32),
    particle_radius: wp.array(dtype=wp.float32),
    particle_alive: wp.array(dtype=wp.int32),
    parcel_eps_s: wp.array(dtype=float),
    cell_volume: wp.float64,
    # outputs
    eps_local: wp.array(dtype=wp.float32),
):
    """The deposited eps_s at the parcel (interpolated with its own stencil S) less its own share,
    w V_p sum_f S_f^2 / V_cell: the real solids fraction of the OTHER parcels around it."""
    tid = wp.tid()
    if particle_alive[tid] == 0:
        eps_local[tid] = wp.float32(0.0)
        return
    w = float(particle_weight[tid])
    base, frac, k, b, norm = parcel_stencil(grid, particle_x[tid], w, tid)
    s2 = wp.float64(0.0)
    for n in range(8 * k * k * k):
        idx, sw = parcel_cell(grid, base, frac, k, b, norm, n)
        s2 = s2 + sw * sw
    own = wp.float64(w * sphere_volume(float(particle_radius[tid]))) * s2 / cell_volume
    eps_local[tid] = wp.float32(wp.max(wp.float64(parcel_eps_s[tid]) - own, wp.float64(0.0)))


def local_solids(grid, particles, parcel_eps_s, eps_local) -> None:
    """``local_solids_kernel`` over ``particles`` (``grid``: the coupling's ``CellGrid`` of the step)."""
    wp.launch(local_solids_kernel, dim=particles.count, device=particles.device,
              inputs=[grid, particles.x, particles.weight, particles.radius, particles.alive, parcel_eps_s,
                      float(grid.spacing) ** 3], outputs=[eps_local])
