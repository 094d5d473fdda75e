"""HELSCM collision kernels: swept (continuous) pair detection with time-ordered resolution, surrogate impulses per
pair, the paper's cluster-averaged mode, per-stream counts.

What it computes (reference paper sec. 4.3; docs/developer/architecture.md "Collision detection"):

- ``pairwise`` (contact form of surrogate/features.py), swept detection: over the step every parcel flies on a
  straight line; a pair collides at the first time its centres come within r_i + r_j while approaching, with
  the contact normal of that moment (docs/physics/references.md "Swept (continuous) detection"), and each parcel then
  follows its new velocity for the rest of the step. Several collisions per parcel are resolved in time order,
  event-driven within the step (the section "swept detection" below). The paper's end-of-step overlap test
  ``|x_i - x_j| < r_i + r_j`` is the same machinery with paths of zero length (every event at t = 0, ties by
  parcel index): ``detection="overlap"`` of hel_warp/collisions/models.py.
  A pair is collided only while approaching: an overlapping pair that already separates (e.g. the one collided
  at the previous step) is skipped - the repeated-detection fix the paper names as missing (its sec. 8).
  The impulse on particle 2 is ``J = m*|g| (impulse_n n + impulse_t t_hat)`` from the forest's two targets
  (``kernels/forest.py`` ``contact_impulse``), ``n`` from 1 to 2. Parcels of weight ``w``: ``min(w_i, w_j)`` real
  binary collisions happen, so parcel i receives ``-min(w_i,w_j) J`` and parcel j ``+min(w_i,w_j) J`` and the
  parcel momentum ``w_i m_i v_i + w_j m_j v_j`` is conserved.
- ``paper`` resolution (sec. 4.3 as written): per parcel the velocities of all overlapping partners
  are summed and averaged (weighted by partner weight), and the paper-form forest maps
  (own velocity, averaged partner velocity, d, mean partner d, rho, mean partner rho) to the new
  velocity. No approach test and no momentum guarantee (the paper's scheme).
- The overlap pair list (``count_pairs``/``fill_pairs``, a compact list i < j, rows sorted by j, independent of
  thread order) that ``hel_warp.collisions.pairs.PairDetector`` builds for the CFD-DEM's end-of-step overlap count.
- Counts (integer atomics, deterministic): pairs overlapping at the step's start, resolved pairs and real
  collisions per stream pair ``(min(s_i, s_j), max(s_i, s_j))``, separating overlaps skipped, rounds.

Launch wrappers at the bottom of each section; they never allocate (hel_warp/collisions/models.py owns the arrays).
"""

from __future__ import annotations

import warp as wp

from kernels.forest import (COS_FEATURE, GUARD_COULOMB, GUARD_ENERGY, GUARD_SEPARATION, SCALE_NONE, ContactDomain, Forest,
                            contact_point_velocity, contact_spin_impulse, spin_guard, turn_spins,
                            write_contact_spin_features_in_domain,
                            admissible_impulse, contact_impulse, scale_factor, sphere_mass, tree_sum,
                            write_contact_features_in_domain)
from kernels.cell_list import CellList, range_count, range_slots, range_slots_pair, search_box, search_box_pair
from kernels.reflect import WallParams, wall_impact
from kernels.sdf import SdfShapes, sdf_shape, sdf_union, sdf_union_normal

PAIR_PENDING = wp.constant(0)
"""``pair_state`` of a detected pair (the overlap pair list of ``hel_warp.collisions.pairs.PairDetector``)."""


@wp.func
def stream_pair_index(s_i: wp.int32, s_j: wp.int32, n_streams: wp.int32):
    """Row-major index of the unordered stream pair (min, max); tags are clamped to [0, n_streams)."""
    a = wp.clamp(wp.min(s_i, s_j), 0, n_streams - 1)
    b = wp.clamp(wp.max(s_i, s_j), 0, n_streams - 1)
    return a * n_streams + b


@wp.func
def minimum_image(d: wp.vec3, periodic: wp.int32, box: wp.vec3):
    """d itself, or its nearest periodic image in a box (component-wise d - L round(d / L))."""
    if periodic == 0:
        return d
    return wp.vec3(d[0] - box[0] * wp.round(d[0] / box[0]), d[1] - box[1] * wp.round(d[1] / box[1]),
                   d[2] - box[2] * wp.round(d[2] / box[2]))


@wp.func
def forest_target(forest: Forest, target: wp.int32, features: wp.array2d(dtype=wp.float32), row: wp.int32):
    """Prediction of one target for one feature row: base_score + sum of the target's tree leaves, times the
    target's scale (kernels/forest.py ``scale_factor``)."""
    acc = tree_sum(forest, forest.tree_start[target], forest.tree_start[target + 1], features, row,
                   forest.base_score[target])
    code = forest.target_scale[target]
    if code != SCALE_NONE:
        acc = acc * scale_factor(code, features[row, COS_FEATURE])
    return acc


# ------------------------------------------------------------------------------------------ detection


@wp.func
def is_new_overlap(particle_x: wp.array(dtype=wp.vec3), particle_radius: wp.array(dtype=wp.float32),
                   particle_alive: wp.array(dtype=wp.int32), i: int, xi: wp.vec3, ri: float, j: int):
    """True for a live partner j > i of parcel i (at xi, radius ri) with |x_i - x_j| < r_i + r_j."""
    if j > i and particle_alive[j] != 0:
        cut = ri + particle_radius[j]
        return wp.length_sq(particle_x[j] - xi) < cut * cut
    return False


@wp.kernel
def count_pairs(
    grid: wp.uint64,
    particle_x: wp.array(dtype=wp.vec3),
    particle_radius: wp.array(dtype=wp.float32),
    particle_alive: wp.array(dtype=wp.int32),
    max_radius: float,
    # outputs
    pair_count: wp.array(dtype=wp.int32),
):
    """pair_count[i] = number of live partners j > i with |x_i - x_j| < r_i + r_j."""
    i = wp.tid()
    c = int(0)
    if particle_alive[i] != 0:
        xi = particle_x[i]
        ri = particle_radius[i]
        for j in wp.hash_grid_query(grid, xi, ri + max_radius):
            if is_new_overlap(particle_x, particle_radius, particle_alive, i, xi, ri, j):
                c = c + 1
    pair_count[i] = c


@wp.kernel
def fill_pairs(
    grid: wp.uint64,
    particle_x: wp.array(dtype=wp.vec3),
    particle_radius: wp.array(dtype=wp.float32),
    particle_alive: wp.array(dtype=wp.int32),
    max_radius: float,
    pair_offset: wp.array(dtype=wp.int32),
    # outputs
    pair_i: wp.array(dtype=wp.int32),
    pair_j: wp.array(dtype=wp.int32),
):
    """Pairs (i, j > i) of row i at pair_offset[i] (exclusive scan of count_pairs), sorted by j."""
    i = wp.tid()
    if particle_alive[i] == 0:
        return
    start = pair_offset[i]
    c = start
    xi = particle_x[i]
    ri = particle_radius[i]
    for j in wp.hash_grid_query(grid, xi, ri + max_radius):
        if is_new_overlap(particle_x, particle_radius, particle_alive, i, xi, ri, j):
            k = c
            while k > start and pair_j[k - 1] > j:  # sorted insert: the row does not depend on query order
                pair_j[k] = pair_j[k - 1]
                k = k - 1
            pair_j[k] = j
            pair_i[c] = i
            c = c + 1


@wp.kernel
def count_detected(
    pair_i: wp.array(dtype=wp.int32),
    pair_j: wp.array(dtype=wp.int32),
    particle_stream: wp.array(dtype=wp.int32),
    n_streams: wp.int32,
    # outputs
    detected: wp.array(dtype=wp.int32),
    pair_state: wp.array(dtype=wp.int32),
):
    """Count each detected pair under its stream pair; mark it pending for the resolution rounds."""
    k = wp.tid()
    s = stream_pair_index(particle_stream[pair_i[k]], particle_stream[pair_j[k]], n_streams)
    wp.atomic_add(detected, s, 1)
    pair_state[k] = PAIR_PENDING


# ------------------------------------------------------------------------------------------ paper mode


@wp.struct
class PaperArgs:
    """Inputs of the paper-mode cluster update."""

    grid: wp.uint64
    particle_x: wp.array(dtype=wp.vec3)
    particle_v: wp.array(dtype=wp.vec3)
    particle_radius: wp.array(dtype=wp.float32)
    particle_density: wp.array(dtype=wp.float32)
    particle_weight: wp.array(dtype=wp.float32)
    particle_alive: wp.array(dtype=wp.int32)
    particle_stream: wp.array(dtype=wp.int32)
    max_radius: float
    n_streams: wp.int32
    periodic: wp.int32
    """1: triply periodic box [0, box) (minimum image; the hash grid tiles the box), 0: open space."""
    box: wp.vec3
    batched: wp.int32
    """1: write each clustered particle's features into the next batch row (``batch_row``, counter
    ``batch_count``) for one batched forest evaluation (``paper_apply_batch``); 0: walk the forest inline."""
    batch_row: wp.array(dtype=wp.int32)
    batch_count: wp.array(dtype=wp.int32)


@wp.kernel
def paper_cluster_update(
    args: PaperArgs,
    forest: Forest,
    # outputs
    features: wp.array2d(dtype=wp.float32),
    particle_v_out: wp.array(dtype=wp.vec3),
    calls: wp.array(dtype=wp.int32),
):
    """Sec. 4.3: partner velocities summed and averaged (weights w_j), then the paper-form forest (u, v, w).

    ``calls[s]`` counts the pairs (j > i) whose stream pair is s (both members get a model call).
    """
    i = wp.tid()
    vi = args.particle_v[i]
    particle_v_out[i] = vi
    if args.batched != 0:
        args.batch_row[i] = -1
    if args.particle_alive[i] == 0:
        return
    xi = args.particle_x[i]
    ri = args.particle_radius[i]
    sum_w = float(0.0)
    sum_v = wp.vec3(0.0)
    sum_d = float(0.0)
    sum_rho = float(0.0)
    for j in wp.hash_grid_query(args.grid, xi, ri + args.max_radius):
        if j != i and args.particle_alive[j] != 0:
            rj = args.particle_radius[j]
            cut = ri + rj
            if wp.length_sq(minimum_image(args.particle_x[j] - xi, args.periodic, args.box)) < cut * cut:
                w = args.particle_weight[j]
                sum_w = sum_w + w
                sum_v = sum_v + w * args.particle_v[j]
                sum_d = sum_d + w * 2.0 * rj
                sum_rho = sum_rho + w * args.particle_density[j]
                if j > i:
                    wp.atomic_add(calls, stream_pair_index(args.particle_stream[i], args.particle_stream[j],
                                                           args.n_streams), 1)
    if sum_w <= 0.0:
        return
    v_avg = sum_v / sum_w
    row = i
    if args.batched != 0:
        row = wp.atomic_add(args.batch_count, 0, 1)  # a row's place changes nothing in its prediction
        args.batch_row[i] = row
    for c in range(3):
        features[row, c] = vi[c]
        features[row, 3 + c] = v_avg[c]
    features[row, 6] = 2.0 * ri
    features[row, 7] = sum_d / sum_w
    features[row, 8] = args.particle_density[i]
    features[row, 9] = sum_rho / sum_w
    if args.batched == 0:
        particle_v_out[i] = wp.vec3(forest_target(forest, 0, features, i), forest_target(forest, 1, features, i),
                                    forest_target(forest, 2, features, i))


@wp.kernel
def paper_apply_batch(
    batch_row: wp.array(dtype=wp.int32),
    batch_out: wp.array2d(dtype=wp.float32),
    # outputs
    particle_v_out: wp.array(dtype=wp.vec3),
):
    """The batched predictions (u, v, w) back to their particles."""
    i = wp.tid()
    row = batch_row[i]
    if row >= 0:
        particle_v_out[i] = wp.vec3(batch_out[row, 0], batch_out[row, 1], batch_out[row, 2])


# ------------------------------------------------------------------------------------------ launch wrappers


def detect_pairs(grid, particles, max_radius: float, pair_count, pair_offset) -> None:
    """Count the overlapping pairs (i < j) per parcel and scan them (exclusive) into ``pair_offset``;
    the total is ``pair_offset[-1] + pair_count[-1]``, read by the host caller."""
    wp.launch(count_pairs, dim=particles.count, device=particles.device,
              inputs=[grid.id, particles.x, particles.radius, particles.alive, float(max_radius)],
              outputs=[pair_count])
    wp.utils.array_scan(pair_count, pair_offset, inclusive=False)


def fill_pair_list(grid, particles, max_radius: float, pair_offset, pair_i, pair_j) -> None:
    wp.launch(fill_pairs, dim=particles.count, device=particles.device,
              inputs=[grid.id, particles.x, particles.radius, particles.alive, float(max_radius), pair_offset],
              outputs=[pair_i, pair_j])


def launch_count_detected(n_pairs: int, pair_i, pair_j, particle_stream, n_streams: int, detected,
                          pair_state) -> None:
    if n_pairs:
        wp.launch(count_detected, dim=n_pairs, device=pair_i.device,
                  inputs=[pair_i, pair_j, particle_stream, int(n_streams)], outputs=[detected, pair_state])


def launch_paper_update(args: PaperArgs, forest: Forest, features, particle_v_out, calls,
                        batch_forest: Forest | None = None, batch_out=None) -> None:
    """Paper-mode update of every particle; with ``batch_forest`` (perfect layout; ``args.batch_*`` and
    ``batch_out`` sized to the particles) the clustered particles are predicted in one batched launch."""
    from kernels.forest import eval_forest

    device = particle_v_out.device
    args.batched = 0 if batch_forest is None else 1
    if batch_forest is not None:
        args.batch_count.zero_()
    wp.launch(paper_cluster_update, dim=args.particle_x.shape[0], device=device,
              inputs=[args, forest], outputs=[features, particle_v_out, calls])
    if batch_forest is not None:
        eval_forest(batch_forest, features, batch_out, device=device, row_count=args.batch_count)
        wp.launch(paper_apply_batch, dim=args.particle_x.shape[0], device=device,
                  inputs=[args.batch_row, batch_out], outputs=[particle_v_out])


# ------------------------------------------------------------------------------------------ swept detection
#
# Swept (continuous) detection, event-driven within the step (docs/physics/references.md "Swept (continuous) detection";
# Alder & Wainwright 1959; Rapaport, *The Art of Molecular Dynamics Simulation*, ch. 14).
# Over the step [0, dt] every parcel moves on a straight line. Its position relative to its hash point
# m = x0 + v0 dt/2 (the midpoint of its initial path, wrapped into the periodic box if any) is
# ``base + v t`` for t >= t_last (its last collision in this step): a collision at time tau changes v to v'
# and base by (v - v') tau, so the path stays continuous at tau, and ``shift`` (the same increments) is the
# correction the host adds to the end-of-step positions after the push moved the parcels with v'.
# A pair (a < b) touches first at the smallest root tau >= t_lo = max(t_last_a, t_last_b) of
# |s(tau)| = r_a + r_b with s(t) = D + base_b - base_a + (v_b - v_a) t (D = m_b - m_a, minimum image in a
# periodic box), provided it approaches (s . ds/dt < 0) and tau <= dt; the contact normal is s(tau)/|s(tau)|.
# Rounds: each dirty parcel (round 0: all) finds its earliest event over its neighbours in the cell list and offers it
# to both parcels with an int64 atomic_min on the key (time quantised to dt/2^30, then partner index: ties go
# to the lower index, deterministic); pairs whose keys point at each other are mutually earliest and are
# resolved together (disjoint by construction) unless a parcel whose path can reach either of them has an earlier
# pending event (it may change course and arrive first: the pair waits - the local-minimum rule of parallel
# event-driven simulation, Lubachevsky 1991). The globally earliest pair always passes, so every round makes
# progress. Parcels that collided, and those whose earliest partner collided, are dirty in the next round.
# Searches after round 0 (and the causality check of every round) must reach every partner k whose path can come
# near: |m_k - m_i| <= r_i + r_k + reach_i + reach_k. One collision can raise a single reach far above the rest,
# and the global max bounded every search; instead a step has a cut R_cut: the cell list (kernels/cell_list.py, the
# live hash points sorted by cell) is searched out to
# r_i + r_max + reach_i + min(R_cut, max reach) and yields the partners of reach <= R_cut, and the "large" parcels
# (reach > R_cut, listed anew at each round's start, so a reach grown past the cut by a collision is listed before
# the next search) are tested one by one. The event search tests a pair with the tighter ``path_bound`` (the
# farthest end of the present path, not reach's |o(t_last)| + path length) and once: in round 0 by the parcel of
# the larger reach, later by the lower index when both are dirty, and later rounds split it by path_bound (a cut
# ``bound_cut`` and its own list: path_bound <= reach, so few are listed). Every pair that can touch is still tested,
# and the causality check keeps its reach test, so the events and rounds are those of the search out to the max.

EVENT_NONE_VALUE = 9223372036854775807
EVENT_NONE = wp.constant(wp.int64(EVENT_NONE_VALUE))
"""``event_key`` of a parcel with no pending event."""
EVENT_TIME_SCALE = wp.constant(1073741824.0)
"""2^30: event times are quantised to dt / 2^30 in the key (the pair's own float time is kept for the impulse)."""


@wp.struct
class SweptArgs:
    """Per-step state of the swept detection (one entry per parcel slot unless said otherwise)."""

    cells: CellList
    """The live parcels' ``anchor`` sorted by cell (kernels/cell_list.py): the searches' candidates."""
    particle_x: wp.array(dtype=wp.vec3)
    particle_radius: wp.array(dtype=wp.float32)
    particle_density: wp.array(dtype=wp.float32)
    particle_weight: wp.array(dtype=wp.float32)
    particle_alive: wp.array(dtype=wp.int32)
    particle_stream: wp.array(dtype=wp.int32)
    particle_omega: wp.array(dtype=wp.vec3)
    """Spins, rad/s (read and updated by the collisions when ``spin`` is 1; the walls' own switch is ``wall.spin``)."""
    spin_form: wp.int32
    """1: a ``contact_spin`` model (8 features, 3 targets: kernels/forest.py ``write_contact_spin_features_in_domain``,
    ``contact_spin_impulse``)."""
    spin: wp.int32
    """1: the particle-particle collisions act at the contact point (docs/physics/spin-and-mixtures.md "Spin in particle-particle
    collisions"): the model is asked at the contact points' relative velocity and the impulse turns the spins."""
    n_streams: wp.int32
    dt: wp.float32
    """The step, s."""
    t_start: wp.float32
    """Start of the present window of the step, s (0 when the step is one window): the step's collisions are resolved
    window after window (``SurrogateCollision`` ``windows``), each with its own searches; a window's events are all
    resolved before the next one's are searched. The paths, event times and outcomes do not depend on the windows."""
    t_end: wp.float32
    """End of the present window, s (``dt`` for the last one): events later than it wait for the next window."""
    first_round: wp.int32
    """The round in which the present window started: its full search (every parcel's pairs, ``swept_find``)."""
    anchor: wp.array(dtype=wp.vec3)
    """The searches' point of each parcel in the present window: its path's position at the window's middle, the
    cell list's point (the ``hash_point`` array itself when the step is one window), m."""
    max_radius: wp.float32
    periodic: wp.int32
    """1: triply periodic box [0, box) (minimum image), 0: open space."""
    box: wp.vec3
    hash_point: wp.array(dtype=wp.vec3)
    """m = x0 + v0 dt/2 (wrapped into the box when periodic), m."""
    base: wp.array(dtype=wp.vec3)
    """Position relative to m is base + v t on [t_last, dt], m."""
    wall_cache: wp.array(dtype=wp.float32)
    """The wall crossing of the parcel's present path over the whole step (``wall_touch`` before its window test:
    the time, or -1 for none), WALL_UNKNOWN until computed; cleared when the path changes (``follow_new_path``), s."""
    shift: wp.array(dtype=wp.vec3)
    """End-of-step position correction sum((v_old - v_new) tau), m."""
    t_last: wp.array(dtype=wp.float32)
    """Time of the parcel's last collision in this step (0 before any), s."""
    frame_velocity: wp.vec3
    """u_f, the mean parcel velocity of the step: reaches are measured in the frame moving with it (Galilean: a
    stream of fast parcels that move together has short reaches), m/s."""
    reach: wp.array(dtype=wp.float32)
    """Bound on |o(t)| over [max(t_last, t_start), t_end], o(t) = position - a - u_f (t - t_mid) (a = ``anchor``,
    t_mid the window's middle: the path relative to the anchor in the moving frame; the u_f terms cancel in a pair's
    separation), m."""
    path_bound: wp.array(dtype=wp.float32)
    """max |o(t)| over [max(t_last, t_start), t_end] of the present path, max(|o(t_last)|, |o(t_end)|) as the path is
    straight (<= reach, which adds the path's length to |o(t_last)|; much less after a turn): the event searches' pair
    test, m."""
    reach_max: wp.array(dtype=wp.float32)
    """(1,) max of ``reach`` (atomic_max; it caps the searches' R_cut), m."""
    reach_cut: wp.float32
    """R_cut: the causality checks' cell-list searches reach the partners of ``reach`` <= R_cut; the larger are
    listed, m."""
    large_index: wp.array(dtype=wp.int32)
    """(n,) the first ``large_count[0]`` entries: every live parcel of ``reach`` > R_cut at the round's start (and
    some below it, skipped by the readers: ``listed``), in any order."""
    large_count: wp.array(dtype=wp.int32)
    """(1,) parcels listed in ``large_index`` (zeroed before each round's ``swept_reset``)."""
    large_point: wp.array(dtype=wp.vec3)
    """(n,) ``anchor`` of each ``large_index`` entry (read in order: the list's distance test without a gather), m."""
    bound_cut: wp.float32
    """The event searches' cut: the cell-list part of a search reaches the partners of ``path_bound`` <= bound_cut,
    the larger are listed (``bound_index``); ``path_bound`` <= ``reach``, so far fewer than ``large_index`` holds, m."""
    bound_index: wp.array(dtype=wp.int32)
    """(n,) the first ``bound_count[0]`` entries: every live parcel of ``path_bound`` > bound_cut at the round's
    start (and some below it, skipped by the readers: ``listed``), in any order."""
    bound_count: wp.array(dtype=wp.int32)
    """(1,) parcels listed in ``bound_index`` (zeroed with ``large_count``)."""
    listed: wp.array(dtype=wp.int32)
    """(n,) bit LISTED_LARGE: the parcel is in ``large_index``, bit LISTED_BOUND: in ``bound_index``. The lists are
    kept over the step's rounds: built in round 0 (``swept_reset``), a parcel added when a collision or a wall event
    raises its reach or path bound above the cut (``swept_mark_dirty``). An entry whose value fell back below the cut
    stays listed; the readers skip it (the grid finds it), so the lists split the candidates exactly as a list
    rebuilt each round would."""
    event_key: wp.array(dtype=wp.int64)
    """Earliest pending event: quantised time << 32 | partner, EVENT_NONE if none."""
    second_key: wp.array(dtype=wp.int64)
    """The second earliest of the events offered to the parcel (``offer_event``); it is the parcel's earliest event
    with any partner but that of ``event_key`` while ``second_ok`` is 1."""
    second_ok: wp.array(dtype=wp.int32)
    """1 while ``second_key`` is exact: set by a full search (round 0, a dirty parcel's), cleared when its partner
    collides or it is promoted to ``event_key`` (``swept_mark_dirty``)."""
    dirty: wp.array(dtype=wp.int32)
    stamp: wp.array(dtype=wp.int32)
    """Round in which the parcel last collided (-1: none yet)."""
    last_partner: wp.array(dtype=wp.int32)
    """Partner of the parcel's last collision in this step (-1: none); overlap detection never repeats a pair
    back to back (at t = 0 a pair bounced back towards its last partner by a third would collide again at once)."""
    round: wp.array(dtype=wp.int32)
    """(1,) current round."""
    max_rounds: wp.int32
    event_i: wp.array(dtype=wp.int32)
    """(rows,) events of the round: parcel a < b, time, normal from a to b."""
    event_j: wp.array(dtype=wp.int32)
    event_time: wp.array(dtype=wp.float32)
    event_normal: wp.array(dtype=wp.vec3)
    batch_count: wp.array(dtype=wp.int32)
    """(1,) events in this round."""
    features: wp.array2d(dtype=wp.float32)
    """(rows, 6) contact features of the round's events ((rows, 8): ``spin_form``)."""
    batch_out: wp.array2d(dtype=wp.float32)
    """(rows, 2) impulse_n, impulse_t of the batch rows (batched evaluation); (rows, 3) with impulse_b: ``spin_form``."""
    batched: wp.int32
    domain: ContactDomain
    """The model's training domain (features clamped into it) and Coulomb bound (the admissibility guard)."""
    guard: wp.array(dtype=wp.int32)
    """(6,) counted: corrections separation, Coulomb, energy (``admissible_impulse`` flags), domain clamps, late
    events (the pair already overlapping at its time t > 0), outcomes turned to their end-of-contact normal."""
    sequential: wp.int32
    """1: one event per round, the globally earliest (strict event-driven order; the reference of the tests)."""
    global_key: wp.array(dtype=wp.int64)
    """(1,) earliest pending event key (``sequential`` only)."""
    blocker: wp.array(dtype=wp.int32)
    """Per parcel a (the lower index of a pending pair): the parcel k whose earlier event blocked the pair, -1."""
    blocker_key: wp.array(dtype=wp.int64)
    """k's event key when it blocked the pair."""
    blocked_key: wp.array(dtype=wp.int64)
    """The pair's key when it was blocked."""
    blocked_round: wp.array(dtype=wp.int32)
    """The round of that check."""
    walls: wp.int32
    """1: wall events in the rounds (a parcel whose path crosses the wall is reflected at the crossing, in time
    order with its collisions); 0: no walls (periodic box, open space) or the push's end-of-step reflection."""
    shapes: SdfShapes
    """The wall geometry (``walls`` = 1; kernels/sdf.py: negative inside the fluid)."""
    wall: WallParams
    """Restitution and Coulomb cap of a parcel-wall impact (kernels/reflect.py ``wall_impact``)."""
    wall_count: wp.array(dtype=wp.int32)
    """(1,) wall events in this round."""
    wall_i: wp.array(dtype=wp.int32)
    """(rows,) parcel of each wall event of the round."""
    wall_time: wp.array(dtype=wp.float32)
    """(rows,) its time in the step, s."""
    wall_hits: wp.array(dtype=wp.int32)
    """(1,) wall events resolved in the step."""


GUARD_CLAMPED = wp.constant(3)
"""Index in ``SweptArgs.guard`` of the domain-clamp count (0-2: the admissibility flags 1, 2, 4)."""
GUARD_TURNED = wp.constant(5)
"""Index in ``SweptArgs.guard`` of the outcomes whose pair was turned to its end-of-contact normal."""
GUARD_LATE = wp.constant(4)
"""Index in ``SweptArgs.guard`` of the events whose pair was already overlapping at its time t > 0 (met unseen)."""
LATE_OVERLAP = wp.constant(0.999)
"""A pair closer than this fraction of r_i + r_j at its event time t > 0 did not meet at first touch."""


@wp.func
def event_key(t: float, dt: float, partner: int):
    """Key ordering events by time, then partner index."""
    q = wp.int64(0)
    if dt > 0.0:
        q = wp.int64(wp.clamp(t / dt, 0.0, 1.0) * EVENT_TIME_SCALE)
    return (q << wp.int64(32)) | wp.int64(partner)


@wp.func
def event_partner(key: wp.int64):
    return wp.int32(key & wp.int64(4294967295))


@wp.func
def offer_event(args: SweptArgs, i: int, key: wp.int64):
    """Offer an event to parcel i: its earliest (``event_key``, atomic_min) and second earliest (``second_key``: what
    the first min displaced or rejected; atomic, so the two are the two smallest offers whatever the order)."""
    old = wp.atomic_min(args.event_key, i, key)
    wp.atomic_min(args.second_key, i, wp.max(old, key))


@wp.func
def relative_position(args: SweptArgs, particle_v: wp.array(dtype=wp.vec3), a: int, b: int, t: float):
    """s(t) = x_b(t) - x_a(t) on the parcels' current paths (a < b), minimum image."""
    d = minimum_image(args.hash_point[b] - args.hash_point[a], args.periodic, args.box)
    return d + (args.base[b] - args.base[a]) + (particle_v[b] - particle_v[a]) * t


NEAR_MARGIN = wp.constant(1.0001)
"""Reach tests are widened by this factor so that float32 round-off of the reaches never drops a pair that meets."""
APPROACH_EPS = wp.constant(1.0e-5)
"""A pair approaches when s.g < -APPROACH_EPS |s| |g|: a pair left touching with a normal velocity of round-off size
(a guard-corrected outcome with no normal rebound) is not collided again at once (no Zeno loop of tiny events);
a real approach that slow has its first touch at b/(r_i + r_j) > 1 - 5e-11."""


@wp.func
def first_touch(args: SweptArgs, particle_v: wp.array(dtype=wp.vec3), a: int, b: int):
    """Earliest time in [t_lo, t_end] at which the pair (a < b) touches while approaching, -1 if none.

    |s0 + g tau| = R with s0 = s(t_lo), g = v_b - v_a, R = r_a + r_b: tau = c / (-s0.g + sqrt((s0.g)^2 - |g|^2 c)),
    c = |s0|^2 - R^2 (the root of docs/physics/references.md in its cancellation-free form); an overlapping approaching pair
    (c <= 0) collides at once, tau = 0."""
    if args.dt <= 0.0:
        # overlap detection (paths of zero length, every event at t = 0): no immediate repeat of a pair
        if args.last_partner[a] == b or args.last_partner[b] == a:
            return -1.0
    t_lo = wp.max(args.t_last[a], args.t_last[b])
    s0 = relative_position(args, particle_v, a, b, t_lo)
    g = particle_v[b] - particle_v[a]
    sg = wp.dot(s0, g)
    if sg >= 0.0:
        return -1.0  # receding (the test below without its square roots)
    if sg >= -APPROACH_EPS * wp.length(s0) * wp.length(g):
        return -1.0
    cut = args.particle_radius[a] + args.particle_radius[b]
    c = wp.dot(s0, s0) - cut * cut
    if c <= 0.0:
        return t_lo
    disc = sg * sg - wp.dot(g, g) * c
    if disc < 0.0:
        return -1.0
    t = t_lo + c / (-sg + wp.sqrt(disc))
    if t > args.t_end:
        return -1.0  # after the window: the next window's searches find it
    return t


WALL_CULL_EPS = wp.constant(1.0e-5)
"""Relative float32 margin of the bisection's shape culling in ``wall_touch``: a shape that close to the bound is
kept, so the culled union never decides a sign the full one would decide otherwise."""
WALL_UNKNOWN = wp.constant(-2.0)
"""``SweptArgs.wall_cache`` of a path whose crossing is not computed yet."""
WALL_BISECTIONS = wp.constant(30)
"""Bisection steps of a wall crossing time (dt / 2^30, below float32's resolution of the step)."""


@wp.func
def path_position(args: SweptArgs, particle_v: wp.array(dtype=wp.vec3), i: int, t: float):
    """Centre of parcel i at time t on its current path (open space: walls are never periodic)."""
    return args.hash_point[i] + args.base[i] + particle_v[i] * t


@wp.func
def wall_distance(args: SweptArgs, i: int, x: wp.vec3):
    """Signed distance of parcel i at x from where the wall acts (> 0 beyond it): the SDF of its centre, plus its
    radius when the wall meets the parcel's surface (``WallParams.surface``, kernels/reflect.py)."""
    d = sdf_union(args.shapes, x)
    if args.wall.surface != 0:
        d = d + args.particle_radius[i]
    return d


@wp.func
def shapes_near_segment(shapes: SdfShapes, x_a: wp.vec3, x_b: wp.vec3, extra: float):
    """Bit mask of the shapes that may hold a point of the segment [x_a, x_b] within the wall's reach (``extra``: the
    radius added when the wall meets the parcel's surface), -1 (all) beyond 30 shapes. A box whose distance at the
    ends exceeds the half length, d_s(a) + d_s(b) > |b - a| (d_s is 1-Lipschitz), is beyond the wall all along the
    segment, so the minimum over the others has the sign of the full union's (``WALL_CULL_EPS``: float32 margin)."""
    if shapes.count > 30:
        return -1
    half_length = 0.5 * wp.length(x_b - x_a)
    margin = WALL_CULL_EPS * (wp.length(x_a) + wp.length(x_b) + half_length + extra)
    mask = int(0)
    for s in range(shapes.count):
        d_a = sdf_shape(shapes, s, x_a)
        d_b = sdf_shape(shapes, s, x_b)
        if 0.5 * (d_a + d_b) - half_length + extra <= margin:
            mask = mask | (1 << s)
    return mask


@wp.func
def bisect_crossing(shapes: SdfShapes, start: wp.vec3, v: wp.vec3, extra: float, lo: float, hi: float, mask: int):
    """The wall crossing of the path start + v t bracketed in [lo, hi] (inside at lo, beyond the wall at hi) by
    WALL_BISECTIONS halvings on the sign of the distance over the shapes of ``mask`` (``shapes_near_segment``; -1:
    all); stops early when float32 holds no time between lo and hi (the rest would change nothing). Returns hi."""
    for _ in range(WALL_BISECTIONS):
        mid = 0.5 * (lo + hi)
        if mid == lo or mid == hi:
            break
        x = start + v * mid
        d = float(1.0e30)
        for s in range(shapes.count):
            if mask == -1 or (mask & (1 << s)) != 0:
                d = wp.min(d, sdf_shape(shapes, s, x))
        if d + extra > 0.0:
            hi = mid
        else:
            lo = mid
    return hi


@wp.func
def path_wall_crossing(args: SweptArgs, particle_v: wp.array(dtype=wp.vec3), i: int):
    """Earliest time in [t_last, dt] at which parcel i's centre crosses the wall moving out of the fluid, -1 if its
    path ends inside at the step's end (the crossing is bracketed on the whole step's path, so its time does not
    depend on the windows) (MP-PIC parcels meet walls as points, kernels/reflect.py; with ``WallParams.surface`` the
    wall acts a particle radius from the centre, ``wall_distance``). A path that starts on or outside
    the wall and moves out crosses at once (t_last); one that starts there moving in (after a wall event) is
    followed to its first inside point. The crossing of a path that ends outside is bracketed by bisection on the
    signed distance (the point just outside is returned: its normal is the wall's; two walls met within a step,
    at a corner, are two events)."""
    t_lo = args.t_last[i]
    d_hi = wall_distance(args, i, path_position(args, particle_v, i, args.dt))
    if d_hi <= 0.0:
        return -1.0
    v = particle_v[i]
    x_lo = path_position(args, particle_v, i, t_lo)
    lo = t_lo
    hi = args.dt
    if wall_distance(args, i, x_lo) >= 0.0:
        if wp.dot(v, sdf_union_normal(args.shapes, x_lo)) > 0.0:
            return t_lo  # t_lo <= t_start <= t_end: in the window
        # on the wall moving in (the point of its last wall event, just outside, or float32 round-off of the new
        # path): the path re-enters at once; an inside point, then the next crossing
        found = int(0)
        for k in range(WALL_BISECTIONS):
            if found == 0:
                t_in = t_lo + (args.dt - t_lo) * wp.pow(0.5, float(WALL_BISECTIONS - k))
                if wall_distance(args, i, path_position(args, particle_v, i, t_in)) < 0.0:
                    lo = t_in
                    found = 1
        if found == 0:
            return -1.0
    extra = float(0.0)
    if args.wall.surface != 0:
        extra = args.particle_radius[i]
    start = args.hash_point[i] + args.base[i]  # path_position's first sum: the same float32 positions
    mask = shapes_near_segment(args.shapes, start + v * lo, start + v * hi, extra)
    hi = bisect_crossing(args.shapes, start, v, extra, lo, hi, mask)
    if wp.dot(v, sdf_union_normal(args.shapes, path_position(args, particle_v, i, hi))) <= 0.0:
        return -1.0
    return hi


@wp.func
def wall_touch(args: SweptArgs, particle_v: wp.array(dtype=wp.vec3), i: int):
    """Parcel i's wall crossing in the window: ``path_wall_crossing`` of its present path (``SweptArgs.wall_cache``:
    computed once per path, as a path's crossing does not depend on the window), -1 when it is after ``t_end``."""
    if args.walls == 0 or args.dt <= 0.0:
        return -1.0
    t = args.wall_cache[i]
    if t == WALL_UNKNOWN:
        t = path_wall_crossing(args, particle_v, i)
        args.wall_cache[i] = t
    if t > args.t_end:
        return -1.0  # after the window: the next window's search finds it
    return t


@wp.kernel
def swept_start(
    args: SweptArgs,
    particle_v: wp.array(dtype=wp.vec3),
    # outputs (the per-parcel arrays of args)
    reach_max: wp.array(dtype=wp.float32),
    reach_sum: wp.array(dtype=wp.float32),
):
    """Initial paths: hash point, base = -v dt/2, reach = |v| dt/2; every live parcel dirty."""
    i = wp.tid()
    args.event_key[i] = EVENT_NONE
    args.second_key[i] = EVENT_NONE
    args.second_ok[i] = 1  # round 0 offers every pair to both parcels
    args.shift[i] = wp.vec3(0.0)
    args.t_last[i] = 0.0
    args.wall_cache[i] = WALL_UNKNOWN
    args.stamp[i] = -1
    args.last_partner[i] = -1
    args.blocker[i] = -1
    args.listed[i] = 0
    v = particle_v[i]
    half = 0.5 * args.dt
    if args.particle_alive[i] == 0:
        args.dirty[i] = 0
        args.reach[i] = 0.0
        args.path_bound[i] = 0.0
        args.base[i] = wp.vec3(0.0)
        args.hash_point[i] = args.particle_x[i]
        return
    m = args.particle_x[i] + v * half
    if args.periodic != 0:
        box = args.box
        m = wp.vec3(m[0] - box[0] * wp.floor(m[0] / box[0]), m[1] - box[1] * wp.floor(m[1] / box[1]),
                    m[2] - box[2] * wp.floor(m[2] / box[2]))
    args.hash_point[i] = m
    args.base[i] = -v * half
    r = wp.length(v - args.frame_velocity) * half
    args.reach[i] = r
    args.path_bound[i] = r
    args.dirty[i] = 1
    wp.atomic_max(reach_max, 0, r)
    wp.atomic_add(reach_sum, 0, r)


@wp.kernel
def swept_window(
    args: SweptArgs,
    particle_v: wp.array(dtype=wp.vec3),
    # outputs (the per-parcel arrays of args)
    reach_max: wp.array(dtype=wp.float32),
    reach_sum: wp.array(dtype=wp.float32),
):
    """Start of a window [t_start, t_end] of a step resolved in several (after ``swept_start``, and after the previous
    window's rounds): every live parcel's anchor (its path's position at the window's middle), reach and path bound
    over the window, keys and lists cleared, dirty (the window's full search). Paths (hash point, base), shifts and
    last-event times carry over: an event's time and outcome do not depend on the windows."""
    i = wp.tid()
    args.event_key[i] = EVENT_NONE
    args.second_key[i] = EVENT_NONE
    args.second_ok[i] = 1
    args.blocker[i] = -1
    args.listed[i] = 0
    if args.particle_alive[i] == 0:
        args.dirty[i] = 0
        args.reach[i] = 0.0
        args.path_bound[i] = 0.0
        args.anchor[i] = args.particle_x[i]
        return
    t_mid = 0.5 * (args.t_start + args.t_end)
    v = particle_v[i]
    m = path_position(args, particle_v, i, t_mid)
    if args.periodic != 0:
        box = args.box
        m = wp.vec3(m[0] - box[0] * wp.floor(m[0] / box[0]), m[1] - box[1] * wp.floor(m[1] / box[1]),
                    m[2] - box[2] * wp.floor(m[2] / box[2]))
    args.anchor[i] = m
    # o(t) = offset + v t - u_f (t - t_mid) is straight over the window (t_last <= t_start): |o| is largest at an end
    offset = minimum_image(args.hash_point[i] - m, args.periodic, args.box) + args.base[i]
    u_f = args.frame_velocity
    o_start = wp.length(offset + v * args.t_start - u_f * (args.t_start - t_mid))
    o_end = wp.length(offset + v * args.t_end - u_f * (args.t_end - t_mid))
    r = wp.max(o_start, o_end)
    args.reach[i] = r
    args.path_bound[i] = r
    args.dirty[i] = 1
    wp.atomic_max(reach_max, 0, r)
    wp.atomic_add(reach_sum, 0, r)


LISTED_LARGE = wp.constant(1)
"""Bit of ``SweptArgs.listed``: the parcel is in ``large_index``."""
LISTED_BOUND = wp.constant(2)
"""Bit of ``SweptArgs.listed``: the parcel is in ``bound_index``."""



@wp.func
def list_far_reaching(args: SweptArgs, i: int):
    """Add a live parcel of reach above the cut to ``large_index`` and one of path bound above the searches' cut to
    ``bound_index``, unless it is listed already (``listed``; one thread per parcel)."""
    if args.particle_alive[i] != 0:
        listed = args.listed[i]
        if args.reach[i] > args.reach_cut and (listed & LISTED_LARGE) == 0:
            slot = wp.atomic_add(args.large_count, 0, 1)
            args.large_index[slot] = i
            args.large_point[slot] = args.anchor[i]
            listed = listed | LISTED_LARGE
        if args.path_bound[i] > args.bound_cut and (listed & LISTED_BOUND) == 0:
            args.bound_index[wp.atomic_add(args.bound_count, 0, 1)] = i
            listed = listed | LISTED_BOUND
        args.listed[i] = listed


@wp.kernel
def swept_reset(args: SweptArgs):
    """Round 0: the far-reaching parcels listed (``list_far_reaching``; every key is EVENT_NONE and nothing listed
    from swept_start). Later rounds add the parcels whose reach a collision raised, in ``swept_mark_dirty``."""
    list_far_reaching(args, wp.tid())


@wp.func
def count_start_overlap(args: SweptArgs, particle_v: wp.array(dtype=wp.vec3), a: int, b: int,
                        detected: wp.array(dtype=wp.int32), skipped: wp.array(dtype=wp.int32)):
    """Count the pair (a < b) if it overlaps at the step's start (the paper's end-of-step test on the previous step's
    end positions), per stream pair, and whether it already separates."""
    s = relative_position(args, particle_v, a, b, 0.0)
    cut = args.particle_radius[a] + args.particle_radius[b]
    if wp.dot(s, s) < cut * cut:
        wp.atomic_add(detected, stream_pair_index(args.particle_stream[a], args.particle_stream[b], args.n_streams), 1)
        if wp.dot(particle_v[b] - particle_v[a], s) >= 0.0:
            wp.atomic_add(skipped, 0, 1)


@wp.func
def paths_near(args: SweptArgs, m_i: wp.vec3, extent_i: float, j: int, m_j: wp.vec3):
    """The paths of i (hash point m_i, extent_i = r_i + path_bound_i) and j (hash point m_j) stay within their bounds
    of their hash points: farther apart than both bounds and radii, they never meet."""
    d = minimum_image(m_j - m_i, args.periodic, args.box)
    near = (extent_i + args.particle_radius[j] + args.path_bound[j]) * NEAR_MARGIN
    return wp.dot(d, d) <= near * near


@wp.func
def offer_pair(args: SweptArgs, particle_v: wp.array(dtype=wp.vec3), i: int, j: int, first: bool,
               detected: wp.array(dtype=wp.int32), skipped: wp.array(dtype=wp.int32)):
    """The pair (i, j) found by i's search: its first touch, if any, offered to both keys (int64 atomic_min); in
    round 0 (``first``) its start overlap is counted."""
    a = wp.min(i, j)
    b = wp.max(i, j)
    if first:
        count_start_overlap(args, particle_v, a, b, detected, skipped)
    t = first_touch(args, particle_v, a, b)
    if t >= 0.0:
        offer_event(args, i, event_key(t, args.dt, j))
        offer_event(args, j, event_key(t, args.dt, i))


@wp.kernel
def swept_find(
    args_store: wp.array(dtype=SweptArgs),
    dirty: wp.array(dtype=wp.int32),
    particle_v: wp.array(dtype=wp.vec3),
    # outputs
    detected: wp.array(dtype=wp.int32),
    skipped: wp.array(dtype=wp.int32),
):
    """Each dirty parcel offers its pair events to both parcels' keys (int64 atomic_min); in round 0 the pairs
    overlapping at the start are counted too (once each: by the parcel of the larger reach, then lower index).
    The candidates are tested nearest first (``paths_near``, the one test that rejects most) and then by the rest,
    so that a far candidate costs few loads. ``args_store``: the step's ``SweptArgs`` (``store_swept_args``), read
    only by the threads that work (``dirty``: ``args.dirty``)."""
    i = wp.tid()
    if dirty[i] == 0:
        return
    args = args_store[0]
    ri = args.particle_radius[i]
    reach_i = args.reach[i]
    mi = args.anchor[i]
    extent_i = ri + args.path_bound[i]
    # the parcel's own wall crossing (wall events): an event whose partner is the parcel itself
    t_wall = wall_touch(args, particle_v, i)
    if t_wall >= 0.0:
        offer_event(args, i, event_key(t_wall, args.dt, i))
    if args.round[0] == args.first_round:
        # every parcel queries (the window's first round): a pair is tested by the parcel of the larger reach (then
        # the lower index), whose search out to r_i + r_max + 2 reach_i finds it; the step's first round counts the
        # start overlaps
        first = args.round[0] == 0
        radius0 = (ri + args.max_radius + 2.0 * reach_i) * NEAR_MARGIN
        lo, hi = search_box(args.cells, mi, radius0)
        for k_range in range(range_count(args.cells, lo, hi)):
            begin, end = range_slots(args.cells, lo, hi, k_range, mi, radius0)
            for slot in range(begin, end):
                j = args.cells.slot_point[slot]
                if j != i:
                    if paths_near(args, mi, extent_i, j, args.cells.slot_position[slot]):
                        reach_j = args.reach[j]
                        if reach_i > reach_j or (reach_i == reach_j and i < j):
                            offer_pair(args, particle_v, i, j, first, detected, skipped)
        return
    # later rounds only dirty parcels query, and must reach every partner: those of path_bound <= bound_cut in the
    # grid (path_bound <= reach <= reach_max), the others in their list; a pair of two dirty parcels is tested by the
    # lower index (the other's search finds it as surely: the rule is symmetric)
    cut = args.bound_cut
    radius = (ri + args.max_radius + args.path_bound[i] + wp.min(cut, args.reach_max[0])) * NEAR_MARGIN
    lo, hi = search_box(args.cells, mi, radius)
    for k_range in range(range_count(args.cells, lo, hi)):
        begin, end = range_slots(args.cells, lo, hi, k_range, mi, radius)
        for slot in range(begin, end):
            j = args.cells.slot_point[slot]
            if j != i:
                if paths_near(args, mi, extent_i, j, args.cells.slot_position[slot]):
                    if args.path_bound[j] <= cut and (j > i or args.dirty[j] == 0):
                        offer_pair(args, particle_v, i, j, False, detected, skipped)
    for slot in range(args.bound_count[0]):
        j = args.bound_index[slot]
        if j != i and args.path_bound[j] > cut:  # below the cut: found in the grid
            if paths_near(args, mi, extent_i, j, args.anchor[j]):
                if j > i or args.dirty[j] == 0:
                    offer_pair(args, particle_v, i, j, False, detected, skipped)


@wp.func
def may_arrive_first(args: SweptArgs, particle_v: wp.array(dtype=wp.vec3), a: int, k: int, t: float, q: wp.int64):
    """True when parcel k has a pending event earlier than a's pair (time bits q, time t) and could, on its new path,
    reach a before t (the bound of ``earlier_neighbour_event``)."""
    key_k = args.event_key[k]
    if key_k == EVENT_NONE or (key_k >> wp.int64(32)) >= q:
        return False
    ra = args.particle_radius[a]
    d = minimum_image(args.anchor[k] - args.anchor[a], args.periodic, args.box)
    near = (ra + args.particle_radius[k] + args.reach[a] + args.reach[k]) * NEAR_MARGIN
    if wp.dot(d, d) > near * near:
        return False
    d = minimum_image(args.hash_point[k] - args.hash_point[a], args.periodic, args.box)  # the paths' own frame
    va = particle_v[a]
    t_k = float(key_k >> wp.int64(32)) / EVENT_TIME_SCALE * args.dt
    t1 = wp.max(t_k, args.t_last[a])
    vk = particle_v[k]
    u_f = args.frame_velocity
    xk = d + args.base[k] + vk * t_k
    xa = args.base[a] + va * t1
    gap = wp.length(xk - xa) - ra - args.particle_radius[k]
    partner_k = event_partner(key_k)
    speed_k = wp.length(vk - u_f) + 2.0 * wp.length(vk - particle_v[partner_k])
    if partner_k == k:  # a wall event: |v'| <= |v_k| (e_n, e_t <= 1), in any direction
        speed_k = wp.length(vk) + wp.length(u_f)
    return gap <= speed_k * (t - t_k) + wp.length(va - u_f) * (t - t1) + 1.0e-6 * ra


@wp.func
def earlier_neighbour_event(args: SweptArgs, particle_v: wp.array(dtype=wp.vec3), a: int, b: int, t: float,
                            q: wp.int64) -> int:
    """A parcel k (not b) that has a pending event at t_k earlier than the pair's (time bits q, time t) and could,
    on its new path, reach a before t, -1 if none. After its event k moves at most V_k = |v_k| + 2 |v_k - v_p| (p its
    partner: an admissible impulse changes k's velocity by at most 2 m_p/(m_k + m_p) |g| <= 2 |g|); a moves at |v_a|.
    From t1 = max(t_k, t_last_a) the gap |x_a(t1) - x_k(t_k)| - r_a - r_k cannot close before
    (V_k (t - t_k) + |v_a| (t - t1)). Returns the first such k of the cell list (reach <= R_cut), else the lowest
    index among the large parcels (their list's order depends on the threads).

    Only parcels whose present paths come within reach of a's are tested: a k whose new path (after its event) leaves
    its present reach could still arrive unseen. Such a miss shows as an event found already overlapping
    (``guard_late_overlap``, resolved at once); none was found in the tests against the strict event order."""
    cut = args.reach_cut
    radius = (args.particle_radius[a] + args.max_radius + args.reach[a] + wp.min(cut, args.reach_max[0])) * NEAR_MARGIN
    ma = args.anchor[a]
    lo, hi = search_box(args.cells, ma, radius)
    for k_range in range(range_count(args.cells, lo, hi)):
        begin, end = range_slots(args.cells, lo, hi, k_range, ma, radius)
        for slot in range(begin, end):
            k = args.cells.slot_point[slot]
            # the key first, here (most candidates have none earlier): no call for them
            if args.event_key[k] >> wp.int64(32) < q:
                if k != a and k != b and may_arrive_first(args, particle_v, a, k, t, q):
                    if args.reach[k] <= cut:
                        return k
    found = int(-1)
    far = (args.particle_radius[a] + args.max_radius + args.reach[a] + args.reach_max[0]) * NEAR_MARGIN
    for slot in range(args.large_count[0]):
        # may_arrive_first's distance test with the largest r_k and reach_k first: most of the list is far away
        d = minimum_image(args.large_point[slot] - ma, args.periodic, args.box)
        if wp.dot(d, d) <= far * far:
            k = args.large_index[slot]
            if k != a and k != b and (found < 0 or k < found) and args.reach[k] > cut:  # below the cut: in the grid
                if may_arrive_first(args, particle_v, a, k, t, q):
                    found = k
    return found


@wp.func
def still_blocked(args: SweptArgs, a: int, key: wp.int64):
    """The pair of a (key) was blocked by parcel k in an earlier round and nothing that decided it has changed: the
    pair's key, k's key, and neither k nor k's partner has collided since (their paths are the same)."""
    k = args.blocker[a]
    if k < 0 or args.blocked_key[a] != key:
        return False
    key_k = args.event_key[k]
    if key_k != args.blocker_key[a] or key_k == EVENT_NONE:
        return False
    since = args.blocked_round[a]
    return args.stamp[k] < since and args.stamp[event_partner(key_k)] < since


@wp.kernel
def swept_global_min(args: SweptArgs):
    """global_key = the earliest pending event of all (``sequential`` resolution: one event per round)."""
    i = wp.tid()
    key = args.event_key[i]
    if key != EVENT_NONE:
        wp.atomic_min(args.global_key, 0, key)


@wp.func
def select_wall_event(args: SweptArgs, particle_v: wp.array(dtype=wp.vec3), a: int, key: wp.int64,
                      events_found: wp.array(dtype=wp.int32)):
    """Parcel a's earliest event is its wall crossing: a row of the round's wall events unless a neighbour with an
    earlier event may reach a first (the causality rule of the pairs)."""
    if args.sequential != 0 and key != args.global_key[0]:
        return
    t = wall_touch(args, particle_v, a)
    if t < 0.0:
        return
    if still_blocked(args, a, key):
        return
    k = earlier_neighbour_event(args, particle_v, a, a, t, key >> wp.int64(32))
    if k >= 0:
        args.blocker[a] = k
        args.blocker_key[a] = args.event_key[k]
        args.blocked_key[a] = key
        args.blocked_round[a] = args.round[0]
        return
    row = wp.atomic_add(args.wall_count, 0, 1)
    args.wall_i[row] = a
    args.wall_time[row] = t
    events_found[0] = 1


@wp.func
def write_event_row(args: SweptArgs, particle_v: wp.array(dtype=wp.vec3), row: int, a: int, b: int, t: float,
                    n: wp.vec3):
    """Event row ``row``: the pair (a < b), its time, contact normal n and contact features (model's domain)."""
    args.event_i[row] = a
    args.event_j[row] = b
    args.event_time[row] = t
    args.event_normal[row] = n
    va = particle_v[a]
    vb = particle_v[b]
    if args.spin != 0:
        va = contact_point_velocity(va, args.particle_omega[a], args.particle_radius[a], n)
        vb = contact_point_velocity(vb, args.particle_omega[b], args.particle_radius[b], -n)
    clamped = int(0)
    if args.spin_form != 0:
        clamped = write_contact_spin_features_in_domain(particle_v[a], particle_v[b], va, vb, n,
                                                        2.0 * args.particle_radius[a], 2.0 * args.particle_radius[b],
                                                        args.particle_density[a], args.particle_density[b],
                                                        args.domain, row, args.features)
    else:
        clamped = write_contact_features_in_domain(va, vb, n, 2.0 * args.particle_radius[a],
                                                   2.0 * args.particle_radius[b], args.particle_density[a],
                                                   args.particle_density[b], args.domain, row, args.features)
    if clamped != 0:
        wp.atomic_add(args.guard, GUARD_CLAMPED, 1)


@wp.kernel
def swept_select(
    args_store: wp.array(dtype=SweptArgs),
    event_key: wp.array(dtype=wp.int64),
    particle_v: wp.array(dtype=wp.vec3),
    # outputs
    events_found: wp.array(dtype=wp.int32),
):
    """Mutually earliest pairs (a < b) become this round's events: time, contact normal, contact features.
    ``args_store``: the step's ``SweptArgs``, read only by the threads of a mutual pair or a wall event
    (``event_key``: ``args.event_key``)."""
    a = wp.tid()
    key = event_key[a]
    if key == EVENT_NONE:
        return
    b = event_partner(key)
    key_b = event_key[b]  # b = a: a wall event
    if b != a:
        if b < a or key_b == EVENT_NONE or event_partner(key_b) != a:
            return
    args = args_store[0]
    if b == a:
        select_wall_event(args, particle_v, a, key, events_found)
        return
    if args.sequential != 0 and key_b != args.global_key[0]:
        return  # the earliest key of all is held by b of the earliest pair: (time, a) < (time, b)
    t = first_touch(args, particle_v, a, b)  # the pair's exact time (the key holds it quantised)
    if t < 0.0:
        return
    # causality: a neighbour with an earlier event may change its path and reach a or b before t; wait for it
    if still_blocked(args, a, key):
        return
    q = key >> wp.int64(32)
    # earlier_neighbour_event of a and of b in one walk of both neighbourhoods (search_box_pair: a candidate near
    # both is read once) and one pass over the list; here in the kernel, not a function (not inlined, it ran 4x slower)
    cut = args.reach_cut
    far = wp.min(cut, args.reach_max[0])
    radius_a = (args.particle_radius[a] + args.max_radius + args.reach[a] + far) * NEAR_MARGIN
    radius_b = (args.particle_radius[b] + args.max_radius + args.reach[b] + far) * NEAR_MARGIN
    ma = args.anchor[a]
    mb = ma + minimum_image(args.anchor[b] - ma, args.periodic, args.box)
    sides = 1 + int(b != a)  # a loop over a and b, not two inlined copies of may_arrive_first
    k = int(-1)
    lo, hi = search_box_pair(args.cells, ma, radius_a, mb, radius_b)
    for k_range in range(range_count(args.cells, lo, hi)):
        begin, end = range_slots_pair(args.cells, lo, hi, k_range, ma, radius_a, mb, radius_b)
        for slot in range(begin, end):
            c = args.cells.slot_point[slot]
            if args.event_key[c] >> wp.int64(32) < q:  # the key first: most candidates have none earlier
                if c != a and c != b and args.reach[c] <= cut:
                    for side in range(sides):
                        if k < 0 and may_arrive_first(args, particle_v, wp.where(side == 0, a, b), c, t, q):
                            k = c
            if k >= 0:
                break
        if k >= 0:
            break
    if k < 0:
        far_a = (args.particle_radius[a] + args.max_radius + args.reach[a] + args.reach_max[0]) * NEAR_MARGIN
        far_b = (args.particle_radius[b] + args.max_radius + args.reach[b] + args.reach_max[0]) * NEAR_MARGIN
        for slot in range(args.large_count[0]):
            d_a = minimum_image(args.large_point[slot] - ma, args.periodic, args.box)
            d_b = minimum_image(args.large_point[slot] - mb, args.periodic, args.box)
            if wp.dot(d_a, d_a) <= far_a * far_a or wp.dot(d_b, d_b) <= far_b * far_b:
                c = args.large_index[slot]
                if c != a and c != b and (k < 0 or c < k) and args.reach[c] > cut:  # below the cut: in the grid
                    for side in range(sides):
                        if may_arrive_first(args, particle_v, wp.where(side == 0, a, b), c, t, q):
                            k = c
    if k >= 0:
        args.blocker[a] = k  # remembered: the check is repeated only once k's event or path changed
        args.blocker_key[a] = args.event_key[k]
        args.blocked_key[a] = key
        args.blocked_round[a] = args.round[0]
        return
    s = relative_position(args, particle_v, a, b, t)
    dist = wp.length(s)
    if dist <= 0.0:
        return
    row = wp.atomic_add(args.batch_count, 0, 1)
    write_event_row(args, particle_v, row, a, b, t, s / dist)
    events_found[0] = 1  # every writer stores the same value


@wp.func
def follow_new_path(args: SweptArgs, i: int, partner: int, t: float, v_old: wp.vec3, v_new: wp.vec3,
                    this_round: int):
    """After a collision at t: base and shift keep the path continuous, reach bounds the rest of the step."""
    dv = (v_old - v_new) * t
    base = args.base[i] + dv
    args.base[i] = base
    args.shift[i] = args.shift[i] + dv
    args.t_last[i] = t
    args.wall_cache[i] = WALL_UNKNOWN
    args.stamp[i] = this_round
    args.last_partner[i] = partner
    u_f = args.frame_velocity
    # the path relative to the window's anchor (the same point when the step is one window: offset 0)
    offset = minimum_image(args.hash_point[i] - args.anchor[i], args.periodic, args.box) + base
    t_mid = 0.5 * (args.t_start + args.t_end)
    o_t = wp.length(offset + v_new * t - u_f * (t - t_mid))
    r = o_t + wp.length(v_new - u_f) * (args.t_end - t)
    args.reach[i] = r
    wp.atomic_max(args.reach_max, 0, r)
    args.path_bound[i] = wp.max(o_t, wp.length(offset + v_new * args.t_end - u_f * (args.t_end - t_mid)))  # o(t), o(t_end)


@wp.func
def end_of_contact_normal(args: SweptArgs, i: int, j: int, t: float, n: wp.vec3, g_after: wp.vec3, mass_i: float,
                          mass_j: float):
    """A grazing soft contact ends with the centre line turned (the spheres slide during the contact; docs/physics/references.md
    "Soft spheres at oblique incidence"): an outcome still closing along the first-touch normal n (g'.n > 0, which
    the DEM shows at grazing incidence and the guard admits up to its slack) leaves the pair touching along the
    nearest normal n' perpendicular to g' instead, the pair turned about its centre of mass (momentum and energy
    untouched, the positions move by at most r_i + r_j times the turn), so it separates and never passes through."""
    g_n = wp.dot(g_after, n)
    g2 = wp.dot(g_after, g_after)
    if g_n <= 0.0 or g2 <= 0.0:
        return
    n_new = n - (g_n / g2) * g_after  # n minus its component along g'
    length = wp.length(n_new)
    if length <= 0.0:
        return
    n_new = n_new / length
    cut = args.particle_radius[i] + args.particle_radius[j]
    ds = cut * (n_new - n)  # change of the relative position x_j - x_i at t
    total = mass_i + mass_j
    move_i = -ds * (mass_j / total)
    move_j = ds * (mass_i / total)
    args.base[i] = args.base[i] + move_i
    args.shift[i] = args.shift[i] + move_i
    args.base[j] = args.base[j] + move_j
    args.shift[j] = args.shift[j] + move_j
    args.reach[i] = args.reach[i] + wp.length(move_i)  # the path moved by move: its bound by as much
    args.reach[j] = args.reach[j] + wp.length(move_j)
    args.path_bound[i] = args.path_bound[i] + wp.length(move_i)
    args.path_bound[j] = args.path_bound[j] + wp.length(move_j)
    wp.atomic_max(args.reach_max, 0, wp.max(args.reach[i], args.reach[j]))
    wp.atomic_add(args.guard, GUARD_TURNED, 1)


@wp.func
def resolve_event_row(args: SweptArgs, forest: Forest, particle_v: wp.array(dtype=wp.vec3),
                      calls: wp.array(dtype=wp.int32), collisions: wp.array(dtype=wp.int32), row: int):
    """Event row ``row`` (``write_event_row``): surrogate impulse, equal and opposite (weights as the pairwise
    rule), new paths."""
    i = args.event_i[row]
    j = args.event_j[row]
    t = args.event_time[row]
    n = args.event_normal[row]
    vi = particle_v[i]
    vj = particle_v[j]
    if t > 0.0:
        # a pair found already overlapping inside the step met unseen: an event out of order (or a start overlap
        # that the previous step's push left); counted, and resolved now
        s_t = relative_position(args, particle_v, i, j, t)
        cut = args.particle_radius[i] + args.particle_radius[j]
        if wp.dot(s_t, s_t) < (cut * LATE_OVERLAP) * (cut * LATE_OVERLAP):
            wp.atomic_add(args.guard, GUARD_LATE, 1)
    impulse_n = float(0.0)
    impulse_t = float(0.0)
    impulse_b = float(0.0)
    moment_t = float(0.0)
    moment_b = float(0.0)
    if args.batched != 0:
        impulse_n = args.batch_out[row, 0]
        impulse_t = args.batch_out[row, 1]
        if args.spin_form != 0:
            impulse_b = args.batch_out[row, 2]
            moment_t = args.batch_out[row, 3]
            moment_b = args.batch_out[row, 4]
    else:
        impulse_n = forest_target(forest, 0, args.features, row)
        impulse_t = forest_target(forest, 1, args.features, row)
        if args.spin_form != 0:
            impulse_b = forest_target(forest, 2, args.features, row)
            if args.spin != 0:
                moment_t = forest_target(forest, 3, args.features, row)
                moment_b = forest_target(forest, 4, args.features, row)
    # admissibility: separating along n, Coulomb, no energy gain, whatever the trees say (kernels/forest.py)
    ri = args.particle_radius[i]
    rj = args.particle_radius[j]
    ci = vi
    cj = vj
    if args.spin != 0:  # the contact points' velocities: the model was asked at them (swept_select)
        ci = contact_point_velocity(vi, args.particle_omega[i], ri, n)
        cj = contact_point_velocity(vj, args.particle_omega[j], rj, -n)
    g = ci - cj
    cos_angle = wp.dot(g, n) / wp.length(g)
    flags = int(0)
    if args.spin != 0 or args.spin_form != 0:
        impulse_n, impulse_t, impulse_b, flags = spin_guard(cos_angle, impulse_n, impulse_t, impulse_b,
                                                            args.domain.friction_bound, args.domain.separation_slack,
                                                            args.spin)
    else:
        impulse_n, impulse_t, flags = admissible_impulse(cos_angle, impulse_n, impulse_t, args.domain.friction_bound,
                                                         args.domain.separation_slack)
    if (flags & GUARD_SEPARATION) != 0:
        wp.atomic_add(args.guard, 0, 1)
    if (flags & GUARD_COULOMB) != 0:
        wp.atomic_add(args.guard, 1, 1)
    if (flags & GUARD_ENERGY) != 0:
        wp.atomic_add(args.guard, 2, 1)
    mi = sphere_mass(2.0 * ri, args.particle_density[i])
    mj = sphere_mass(2.0 * rj, args.particle_density[j])
    J = wp.vec3(0.0)
    if args.spin != 0 or args.spin_form != 0:
        J = contact_spin_impulse(vi, vj, ci, cj, n, mi, mj, impulse_n, impulse_t, impulse_b)  # on j; i gets -J
    else:
        J = contact_impulse(ci, cj, n, mi, mj, impulse_n, impulse_t)  # on j; i gets -J
    wi = args.particle_weight[i]
    wj = args.particle_weight[j]
    w_min = wp.min(wi, wj)
    vi_new = vi - J * (w_min / (wi * mi))
    vj_new = vj + J * (w_min / (wj * mj))
    particle_v[i] = vi_new
    particle_v[j] = vj_new
    if args.spin != 0:
        J_rot = J
        if args.spin_form != 0:
            J_rot = contact_spin_impulse(vi, vj, ci, cj, n, mi, mj, 0.0, moment_t, moment_b)
        wi_new, wj_new, fell_back = turn_spins(vi, vj, vi_new, vj_new, args.particle_omega[i], args.particle_omega[j],
                                               n, ri, rj, mi, mj, wi, wj, w_min / wi, w_min / wj, J, J_rot)
        args.particle_omega[i] = wi_new
        args.particle_omega[j] = wj_new
        if fell_back != 0:
            wp.atomic_add(args.guard, 2, 1)
    this_round = args.round[0]
    follow_new_path(args, i, j, t, vi, vi_new, this_round)
    follow_new_path(args, j, i, t, vj, vj_new, this_round)
    end_of_contact_normal(args, i, j, t, n, vi_new - vj_new, mi * wi, mj * wj)
    s = stream_pair_index(args.particle_stream[i], args.particle_stream[j], args.n_streams)
    wp.atomic_add(calls, s, 1)
    wp.atomic_add(collisions, s, wp.int32(w_min + 0.5))


@wp.kernel
def swept_resolve(
    args_store: wp.array(dtype=SweptArgs),
    batch_count: wp.array(dtype=wp.int32),
    forest: Forest,
    # outputs
    particle_v: wp.array(dtype=wp.vec3),
    calls: wp.array(dtype=wp.int32),
    collisions: wp.array(dtype=wp.int32),
):
    """The round's events: surrogate impulse, equal and opposite (weights as the pairwise rule), new paths.
    ``batch_count``: ``args.batch_count``."""
    row = wp.tid()
    if row >= batch_count[0]:
        return
    resolve_event_row(args_store[0], forest, particle_v, calls, collisions, row)


@wp.kernel
def swept_log_events(
    args_store: wp.array(dtype=SweptArgs),
    batch_count: wp.array(dtype=wp.int32),
    particle_v: wp.array(dtype=wp.vec3),
    # outputs
    count: wp.array(dtype=wp.int32),
    log_int: wp.array2d(dtype=wp.int32),
    log_float: wp.array2d(dtype=wp.float32),
):
    """The round's events as they are about to be resolved (launched before ``swept_resolve``): per event one row of
    ``log_int`` (slot i, slot j, stream of i, stream of j) and of ``log_float`` (normal approach speed |(v_i - v_j) . n|,
    time in the step, s); ``count[0]`` counts every event, rows past the arrays' length are dropped."""
    row = wp.tid()
    if row >= batch_count[0]:
        return
    args = args_store[0]
    i = args.event_i[row]
    j = args.event_j[row]
    k = wp.atomic_add(count, 0, 1)
    if k < log_int.shape[0]:
        g = particle_v[i] - particle_v[j]
        log_int[k, 0] = i
        log_int[k, 1] = j
        log_int[k, 2] = args.particle_stream[i]
        log_int[k, 3] = args.particle_stream[j]
        log_float[k, 0] = wp.abs(wp.dot(g, args.event_normal[row]))
        log_float[k, 1] = args.event_time[row]


@wp.func
def resolve_wall_row(args: SweptArgs, particle_v: wp.array(dtype=wp.vec3), particle_omega: wp.array(dtype=wp.vec3),
                     row: int):
    """Wall event row ``row``: the parcel reflected at its crossing, its new path from there."""
    i = args.wall_i[row]
    t = args.wall_time[row]
    v = particle_v[i]
    n = sdf_union_normal(args.shapes, path_position(args, particle_v, i, t))
    if wp.dot(v, n) <= 0.0:
        return
    omega = wp.vec3(0.0, 0.0, 0.0)
    if args.wall.spin != 0:
        omega = particle_omega[i]
    v_new, omega_new = wall_impact(args.wall, v, omega, n, args.particle_radius[i])
    particle_v[i] = v_new
    if args.wall.spin != 0:
        particle_omega[i] = omega_new
    follow_new_path(args, i, i, t, v, v_new, args.round[0])
    wp.atomic_add(args.wall_hits, 0, 1)


@wp.kernel
def swept_resolve_walls(
    args_store: wp.array(dtype=SweptArgs),
    wall_count: wp.array(dtype=wp.int32),
    # outputs
    particle_v: wp.array(dtype=wp.vec3),
    particle_omega: wp.array(dtype=wp.vec3),
):
    """The round's wall events: the parcel reflected at its crossing (e_n, e_t, Coulomb cap as the push's
    reflection, or the rough-sphere law with spin of ``args.wall.spin``: kernels/reflect.py ``wall_impact``), its new
    path from there. ``wall_count``: ``args.wall_count``; ``particle_omega``: updated with ``args.wall.spin``."""
    row = wp.tid()
    if row >= wall_count[0]:
        return
    resolve_wall_row(args_store[0], particle_v, particle_omega, row)


@wp.kernel
def swept_mark_dirty(
    args_store: wp.array(dtype=SweptArgs),
    round_now: wp.array(dtype=wp.int32),
    stamp: wp.array(dtype=wp.int32),
    event_key: wp.array(dtype=wp.int64),
    # outputs
    dirty: wp.array(dtype=wp.int32),
):
    """Dirty next round: parcels that collided in this round, and those whose pending partner did unless their exact
    second event (``second_key``, its partner unmoved) takes the place of the first: every pair whose path did not
    change keeps its time, and the colliders' searches offer the pairs that did, so the keys after the next
    swept_find are those of a full search. A dirty parcel forgets its events (its search of the next round finds
    them again, or new ones; its second is then exact again); a collider whose reach rose above the cut is added to
    the far-reaching lists for the next round (``list_far_reaching``). Each thread reads and writes its own keys only,
    so the reset of a round's start is this kernel, not one more over the parcels; a parcel with no event that did
    not collide (most of them) only clears its flag, without reading ``args_store`` (the step's ``SweptArgs``;
    ``round_now``, ``stamp``, ``event_key``, ``dirty``: its arrays of those names)."""
    i = wp.tid()
    this_round = round_now[0]
    stamped = stamp[i] == this_round
    if not stamped and event_key[i] == EVENT_NONE:
        # no event and no collision (most parcels, the dead ones too): clean, nothing listed anew
        if dirty[i] != 0:
            dirty[i] = 0
        return
    args = args_store[0]
    is_dirty = int(0)
    if args.particle_alive[i] != 0:
        key = args.event_key[i]
        second = args.second_key[i]
        if stamped:
            is_dirty = 1
        elif key != EVENT_NONE:
            second_moved = second != EVENT_NONE and args.stamp[event_partner(second)] == this_round
            if args.stamp[event_partner(key)] == this_round:
                if args.second_ok[i] == 0 or second_moved:
                    is_dirty = 1
                else:
                    # no third event is known: the second is exact again only if there was none
                    args.event_key[i] = second
                    args.second_key[i] = EVENT_NONE
                    if second != EVENT_NONE:
                        args.second_ok[i] = 0
            elif second_moved:
                args.second_ok[i] = 0
    dirty[i] = is_dirty
    if is_dirty != 0:
        args.event_key[i] = EVENT_NONE
        args.second_key[i] = EVENT_NONE
        args.second_ok[i] = 1
    if stamped:
        list_far_reaching(args, i)  # its collision or wall event changed its reach and path bound


@wp.kernel
def swept_bump_round(round_now: wp.array(dtype=wp.int32)):
    """round += 1 (the serial queue: its window's full search was a round; the step's start-overlap census is
    round 0's only)."""
    round_now[0] = round_now[0] + 1


@wp.kernel
def swept_next_round(
    args: SweptArgs,
    # outputs
    events_found: wp.array(dtype=wp.int32),
    event_rounds: wp.array(dtype=wp.int32),
    round_cap_hit: wp.array(dtype=wp.int32),
):
    """Next round (its event and wall rows zeroed); counts the rounds that resolved events; stops at ``max_rounds``
    (and says so)."""
    r = args.round[0] + 1
    args.round[0] = r
    args.batch_count[0] = 0
    args.wall_count[0] = 0
    if events_found[0] != 0:
        event_rounds[0] = event_rounds[0] + 1
        if r >= args.max_rounds:
            events_found[0] = 0
            round_cap_hit[0] = 1


@wp.kernel
def add_shift(
    shift: wp.array(dtype=wp.vec3),
    particle_alive: wp.array(dtype=wp.int32),
    # outputs
    particle_x: wp.array(dtype=wp.vec3),
):
    """End-of-step positions of the swept paths: x += shift (the push moved the parcels with the new v)."""
    i = wp.tid()
    if particle_alive[i] != 0:
        particle_x[i] = particle_x[i] + shift[i]


@wp.kernel
def add_swept_shift(
    shift: wp.array(dtype=wp.vec3),
    t_last: wp.array(dtype=wp.float32),
    v_swept: wp.array(dtype=wp.vec3),
    particle_alive: wp.array(dtype=wp.int32),
    particle_v: wp.array(dtype=wp.vec3),
    # outputs
    particle_x: wp.array(dtype=wp.vec3),
):
    """End-of-step positions of the swept paths after a push that changed v (drag, gravity): the push moved the
    parcel by v_push dt from its start; the swept path is base + v_swept t, with its last event at t_last. The
    velocity change of the push acts over the rest of the step only, (v_push - v_swept)(dt - t_last), not over
    the part of the path before the last event: x += shift - (v_push - v_swept) t_last. (Applied over the whole
    step, a strong drag (dt / tau ~ 1 in the rig's dense cloud at 1e-3 s) pulls a pair that collided late in the
    step back by up to g' dt: thousands of deep overlaps per step that re-collide at once.) With v_push = v_swept
    (no forces: the cooling box) this is ``add_shift``."""
    i = wp.tid()
    if particle_alive[i] != 0:
        particle_x[i] = particle_x[i] + shift[i] - (particle_v[i] - v_swept[i]) * t_last[i]


@wp.kernel
def drift_swept(
    shift: wp.array(dtype=wp.vec3),
    particle_alive: wp.array(dtype=wp.int32),
    particle_v: wp.array(dtype=wp.vec3),
    dt: float,
    # outputs
    particle_x: wp.array(dtype=wp.vec3),
):
    """End of a step whose velocities were pushed before the collisions: the parcels move to their swept paths'
    ends, x += v dt + shift."""
    i = wp.tid()
    if particle_alive[i] != 0:
        particle_x[i] = particle_x[i] + particle_v[i] * dt + shift[i]


@wp.kernel
def store_swept_args(
    args: SweptArgs,
    # outputs
    args_store: wp.array(dtype=SweptArgs),
):
    """args_store[0] = args: the round kernels take the step's ``SweptArgs`` from a one-element array, so that only
    the threads that work copy it (a kernel argument struct is copied by every CPU thread, ~10 ns for this one;
    most threads of a round exit at once)."""
    args_store[0] = args


def launch_swept_start(args: SweptArgs, particle_v, reach_max, reach_sum) -> None:
    """Initial paths of every parcel; ``reach_max`` / ``reach_sum`` (zeroed by the caller) get the max and the sum
    of |v| dt / 2 (the sum only sizes the hash cells: its summation order changes no result)."""
    wp.launch(swept_start, dim=particle_v.shape[0], device=particle_v.device, inputs=[args, particle_v],
              outputs=[reach_max, reach_sum])


def launch_swept_window(args: SweptArgs, particle_v, reach_max, reach_sum) -> None:
    """A window's start (``swept_window``); ``reach_max`` / ``reach_sum`` (zeroed by the caller) as ``swept_start``."""
    wp.launch(swept_window, dim=particle_v.shape[0], device=particle_v.device, inputs=[args, particle_v],
              outputs=[reach_max, reach_sum])


def resolve_swept(args: SweptArgs, forest: Forest, particle_v, events_found, event_rounds, round_cap_hit, calls,
                  collisions, detected, skipped, batch_forest: Forest | None = None, args_store=None,
                  particle_omega=None, event_log=None, queue=None) -> None:
    """Rounds of mutually earliest events until none is left (``wp.capture_while``: a while node where the call is
    captured into a graph - tests/test_device_paths.py does, on the CPU; the engine calls it uncaptured, a host loop
    with one device read per round) or
    ``args.max_rounds`` is reached (then ``round_cap_hit`` is set). ``args.cells`` must hold ``args.anchor``;
    ``args.reach_cut`` >= 0 splits the searches between the grid and the list of large parcels (the events do not
    depend on it).
    Round 0 also counts the pairs overlapping at the start into ``detected`` (per stream pair) and ``skipped``.

    With ``batch_forest`` (perfect layout) each round's events are predicted in one batched evaluation.
    ``particle_omega``: the parcels' spins, updated by the wall events when ``args.wall.spin`` is set (needed then).
    ``event_log``: None, or ``(count, log_int, log_float)`` that ``swept_log_events`` fills with every event resolved
    (``count`` zeroed by the caller).

    ``queue=(heap_key, heap_owner, heap_size)`` (int64 keys and int32 owners of a heap of more than n entries, its
    size): the serial
    resolution instead of the rounds: the window's full search (``swept_find``), then ``swept_queue`` on one thread,
    the events one by one in time order (``event_rounds`` counts them: each is a round of the strict order). The
    strict order's result bit for bit, at a cost per event: the CPU's resolution (a GPU runs the rounds).

    Every launch of a round is recorded once per call (``record_cmd``: the arguments, ``args`` included, are
    packed once, as they stay the same over the step) and replayed each round: on the CPU packing the
    ``SweptArgs`` struct cost ~40-80 us per launch, i.e. ~0.3 ms per round of the rig's 100-200 rounds per step.
    The round kernels launched over every parcel read ``args`` from ``args_store`` (a one-element array, written
    here; allocated if None) in the threads that work only: a struct kernel argument is copied by every CPU
    thread (~10 ns for ``SweptArgs``), and most threads of a round have nothing to do."""
    device = particle_v.device
    n = particle_v.shape[0]
    args.batched = 0 if batch_forest is None or queue is not None else 1
    if args_store is None:
        args_store = wp.empty(1, dtype=SweptArgs, device=device)
    wp.launch(store_swept_args, dim=1, device=device, inputs=[args], outputs=[args_store])

    if particle_omega is None:
        if args.walls != 0 and args.wall.spin != 0:
            raise ValueError("wall spin (args.wall.spin) needs particle_omega")
        particle_omega = wp.zeros(1, dtype=wp.vec3, device=device)
    args.large_count.zero_()
    args.bound_count.zero_()
    args.batch_count.zero_()
    args.wall_count.zero_()
    wp.launch(swept_reset, dim=n, device=device, inputs=[args])  # round 0's lists; later rounds' in mark_dirty
    if queue is not None:
        from kernels.swept_queue import swept_queue  # its own module: a CUDA device never compiles it

        # the window's full search (every parcel's earliest event), then the events one by one
        wp.launch(swept_find, dim=n, device=device, inputs=[args_store, args.dirty, particle_v],
                  outputs=[detected, skipped])
        wp.launch(swept_bump_round, dim=1, device=device, inputs=[args.round])  # the next window's is not round 0
        heap_key, heap_owner, heap_size = queue
        max_pops = max(64 * n, 1_000_000)  # an inelastic collapse would pop for ever
        wp.launch(swept_queue, dim=1, device=device,
                  inputs=[args_store, forest, heap_key, heap_owner, heap_size, max_pops],
                  outputs=[particle_v, particle_omega, calls, collisions, event_rounds, round_cap_hit])
        return

    def record(kernel, dim, inputs, outputs=()):
        return wp.launch(kernel, dim=dim, device=device, inputs=inputs, outputs=list(outputs), record_cmd=True)

    find = record(swept_find, n, [args_store, args.dirty, particle_v], [detected, skipped])
    global_min = record(swept_global_min, n, [args]) if args.sequential != 0 else None
    select = record(swept_select, n, [args_store, args.event_key, particle_v], [events_found])
    predict = None
    if batch_forest is not None:
        from kernels.forest import eval_forest

        predict = eval_forest(batch_forest, args.features, args.batch_out, device=device, row_count=args.batch_count,
                              record=True)
    log = (record(swept_log_events, n // 2 + 1, [args_store, args.batch_count, particle_v], list(event_log))
           if event_log is not None else None)
    resolve = record(swept_resolve, n // 2 + 1, [args_store, args.batch_count, forest],
                     [particle_v, calls, collisions])  # pairs: <= n/2 rows
    walls = (record(swept_resolve_walls, n, [args_store, args.wall_count], [particle_v, particle_omega])
             if args.walls != 0 else None)
    mark_dirty = record(swept_mark_dirty, n, [args_store, args.round, args.stamp, args.event_key], [args.dirty])
    next_round = record(swept_next_round, 1, [args], [events_found, event_rounds, round_cap_hit])

    def one_round():
        find.launch()
        events_found.zero_()
        if global_min is not None:
            args.global_key.fill_(EVENT_NONE_VALUE)
            global_min.launch()
        select.launch()
        if predict is not None:
            predict.launch()
        if log is not None:
            log.launch()
        resolve.launch()
        if walls is not None:
            walls.launch()
        mark_dirty.launch()
        next_round.launch()

    events_found.fill_(1)
    wp.capture_while(events_found, one_round)


def launch_add_shift(shift, particle_alive, particle_x) -> None:
    wp.launch(add_shift, dim=particle_x.shape[0], device=particle_x.device, inputs=[shift, particle_alive],
              outputs=[particle_x])


def launch_drift_swept(shift, particle_alive, particle_v, dt: float, particle_x) -> None:
    wp.launch(drift_swept, dim=particle_x.shape[0], device=particle_x.device,
              inputs=[shift, particle_alive, particle_v, float(dt)], outputs=[particle_x])


def launch_add_swept_shift(shift, t_last, v_swept, particle_alive, particle_v, particle_x) -> None:
    wp.launch(add_swept_shift, dim=particle_x.shape[0], device=particle_x.device,
              inputs=[shift, t_last, v_swept, particle_alive, particle_v], outputs=[particle_x])
