"""HELSCM collision kernels: end-of-step pair detection, surrogate impulses per pair, per-stream counts.

What it computes (reference paper sec. 4.3; ARCHITECTURE.md "The step", item 4):

- Detection: every pair of live parcels with ``|x_i - x_j| < r_i + r_j`` (the paper's
  ``|P_A P_B| < r_A + r_B``), found on a ``wp.HashGrid`` (cell size ``2 r_max``). The compact
  pair list holds ``i < j`` only, each row sorted by ``j``, so a pair appears exactly once and
  the list does not depend on thread order.
- ``pairwise`` resolution (contact form of surrogate/features.py): the pairs are resolved in
  rounds of *disjoint* pairs (a greedy matching: a pending pair is taken in a round when it has
  the lowest pair index among the pending pairs of both its parcels - integer ``atomic_min``,
  deterministic). The lowest pending pair is always taken, so every round makes progress and the
  loop ends after at most as many rounds as pairs (typically the largest number of partners of a
  parcel). Inside a round no parcel is touched twice, so each impulse is applied once to velocities
  that already carry the earlier rounds (sequential impulses, Gauss-Seidel order by pair index):
  no double counting, and each parcel pair exchanges an equal and opposite impulse, so the total
  momentum is conserved to float32 round-off of the velocity updates.
  A pair is collided only while approaching, ``(v_j - v_i).(x_j - x_i) < 0``: an overlapping
  pair that already separates (e.g. the one collided last step) is skipped - the repeated-detection
  fix the paper names as missing (its sec. 8).
  The impulse on particle 2 is ``J = m*|g| (impulse_n n + impulse_t t_hat)`` from the forest's two
  targets (``kernels/forest.py`` ``contact_impulse``), ``n`` from 1 to 2 along the centre line.
  Parcels of weight ``w``: ``min(w_i, w_j)`` real binary collisions happen (each real particle of the
  parcel with fewer particles meets one of the other), so parcel i receives ``-min(w_i,w_j) J`` and
  parcel j ``+min(w_i,w_j) J``: ``dv_i = -(min/w_i) J/m_i``, ``dv_j = +(min/w_j) J/m_j`` and the parcel
  momentum ``w_i m_i v_i + w_j m_j v_j`` is conserved.
- ``paper`` resolution (sec. 4.3 as written): per parcel the velocities of all overlapping partners
  are summed and averaged (weighted by partner weight), and the paper-form forest maps
  (own velocity, averaged partner velocity, d, mean partner d, rho, mean partner rho) to the new
  velocity. No approach test and no momentum guarantee (the paper's scheme).
- Counts (integer atomics, deterministic): detected pairs and surrogate calls per stream pair
  ``(min(s_i, s_j), max(s_i, s_j))``, separating pairs skipped, matching rounds.

Launch wrappers at the bottom; they never allocate (hel_warp/collision_models.py owns the arrays).
"""

from __future__ import annotations

import warp as wp

from kernels.forest import Forest, contact_impulse, sphere_mass, walk_tree

PAIR_NONE = wp.constant(2147483647)
"""``owner`` value of a parcel no pending pair has claimed in this round."""
PAIR_PENDING = wp.constant(0)
PAIR_DONE = wp.constant(1)


@wp.func
def stream_pair_index(s_i: wp.int32, s_j: wp.int32, n_streams: wp.int32):
    """Row-major index of the unordered stream pair (min, max); tags are clamped to [0, n_streams)."""
    a = wp.clamp(wp.min(s_i, s_j), 0, n_streams - 1)
    b = wp.clamp(wp.max(s_i, s_j), 0, n_streams - 1)
    return a * n_streams + b


@wp.func
def forest_target(forest: Forest, target: wp.int32, features: wp.array2d(dtype=wp.float32), row: wp.int32):
    """Prediction of one target for one feature row: base_score + sum of the target's tree leaves."""
    acc = forest.base_score[target]
    for k in range(forest.tree_start[target], forest.tree_start[target + 1]):
        acc = acc + walk_tree(forest, forest.tree_root[k], features, row)
    return acc


@wp.func
def write_contact_features(v1: wp.vec3, v2: wp.vec3, n: wp.vec3, d1: float, d2: float, rho1: float, rho2: float,
                           row: wp.int32, features: wp.array2d(dtype=wp.float32)):
    """Contact-frame features g_n, g_t, g_n/|g|, d1, d2/d1, rho2/rho1 (as kernels/forest.py contact_features)."""
    g = v1 - v2
    g_n = wp.dot(g, n)
    gt = g - g_n * n
    gt = gt - wp.dot(gt, n) * n
    features[row, 0] = g_n
    features[row, 1] = wp.length(gt)
    features[row, 2] = g_n / wp.length(g)
    features[row, 3] = d1
    features[row, 4] = d2 / d1
    features[row, 5] = rho2 / rho1


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


# ------------------------------------------------------------------------------------------ pairwise mode


@wp.kernel
def reset_owner(
    # outputs
    owner: wp.array(dtype=wp.int32),
    more_rounds: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    owner[i] = PAIR_NONE
    if i == 0:
        more_rounds[0] = 0


@wp.kernel
def claim_pairs(
    pair_i: wp.array(dtype=wp.int32),
    pair_j: wp.array(dtype=wp.int32),
    pair_state: wp.array(dtype=wp.int32),
    # outputs
    owner: wp.array(dtype=wp.int32),
):
    """Each parcel remembers the lowest pending pair index touching it (integer atomic_min)."""
    k = wp.tid()
    if pair_state[k] == PAIR_PENDING:
        wp.atomic_min(owner, pair_i[k], k)
        wp.atomic_min(owner, pair_j[k], k)


@wp.struct
class PairwiseArgs:
    """Inputs of one resolution round (pairwise mode)."""

    pair_i: wp.array(dtype=wp.int32)
    pair_j: wp.array(dtype=wp.int32)
    owner: wp.array(dtype=wp.int32)
    particle_x: wp.array(dtype=wp.vec3)
    particle_radius: wp.array(dtype=wp.float32)
    particle_density: wp.array(dtype=wp.float32)
    particle_weight: wp.array(dtype=wp.float32)
    particle_stream: wp.array(dtype=wp.int32)
    n_streams: wp.int32
    batched: wp.int32
    """1: the round's forest predictions come from one batched evaluation (``select_round``), 0: inline walks."""
    batch_row: wp.array(dtype=wp.int32)
    """(pairs,) row of the pair in this round's batch, -1 if it is not evaluated in this round."""
    batch_count: wp.array(dtype=wp.int32)
    """(1,) rows in this round's batch."""
    batch_features: wp.array2d(dtype=wp.float32)
    """(pairs, 6) the batch's contact features, rows 0 .. batch_count - 1 (the ``features`` array that
    inline walks use; a round is either batched or inline)."""
    batch_out: wp.array2d(dtype=wp.float32)
    """(pairs, 2) impulse_n, impulse_t of the batch rows."""


@wp.func
def owns_both(args: PairwiseArgs, k: int):
    """Pair k holds the lowest pending index at both its parcels: it is resolved in this round."""
    return args.owner[args.pair_i[k]] == k and args.owner[args.pair_j[k]] == k


@wp.func
def pair_now(args: PairwiseArgs, particle_v: wp.array(dtype=wp.vec3), k: int):
    """Pair k at the current velocities: i, j, d = x_j - x_i, |d|, v_i, v_j."""
    i = args.pair_i[k]
    j = args.pair_j[k]
    d = args.particle_x[j] - args.particle_x[i]
    return i, j, d, wp.length(d), particle_v[i], particle_v[j]


@wp.func
def approaching(d: wp.vec3, dist: float, vi: wp.vec3, vj: wp.vec3):
    """Centres apart (d = x_j - x_i, dist = |d| > 0) and closing: (v_j - v_i).(x_j - x_i) < 0."""
    return dist > 0.0 and wp.dot(vj - vi, d) < 0.0


@wp.kernel
def select_round(
    args: PairwiseArgs,
    particle_v: wp.array(dtype=wp.vec3),
    pair_state: wp.array(dtype=wp.int32),
    # outputs
    more_rounds: wp.array(dtype=wp.int32),
):
    """The pending pairs that own both their parcels and approach: contact features into the next batch row
    (an atomic counter; a row's place changes nothing in its prediction), for one batched forest
    evaluation of the round. Pairs that wait for a later round ask for one."""
    k = wp.tid()
    args.batch_row[k] = -1
    if pair_state[k] != PAIR_PENDING:
        return
    if not owns_both(args, k):
        more_rounds[0] = 1  # every writer stores the same value
        return
    i, j, d, dist, vi, vj = pair_now(args, particle_v, k)
    if not approaching(d, dist, vi, vj):
        return
    row = wp.atomic_add(args.batch_count, 0, 1)
    args.batch_row[k] = row
    write_contact_features(vi, vj, d / dist, 2.0 * args.particle_radius[i], 2.0 * args.particle_radius[j],
                           args.particle_density[i], args.particle_density[j], row, args.batch_features)


@wp.kernel
def resolve_round(
    args: PairwiseArgs,
    forest: Forest,
    # outputs
    pair_state: wp.array(dtype=wp.int32),
    features: wp.array2d(dtype=wp.float32),
    particle_v: wp.array(dtype=wp.vec3),
    calls: wp.array(dtype=wp.int32),
    skipped: wp.array(dtype=wp.int32),
    more_rounds: wp.array(dtype=wp.int32),
):
    """Resolve the pending pairs that own both their parcels (disjoint: each parcel is written once)."""
    k = wp.tid()
    if pair_state[k] != PAIR_PENDING:
        return
    if not owns_both(args, k):
        more_rounds[0] = 1  # every writer stores the same value
        return
    pair_state[k] = PAIR_DONE
    i, j, d, dist, vi, vj = pair_now(args, particle_v, k)
    if not approaching(d, dist, vi, vj):
        wp.atomic_add(skipped, 0, 1)  # separating (or coincident centres: no normal): not collided
        return
    n = d / dist
    ri = args.particle_radius[i]
    rj = args.particle_radius[j]
    rho_i = args.particle_density[i]
    rho_j = args.particle_density[j]
    impulse_n = float(0.0)
    impulse_t = float(0.0)
    if args.batched != 0:
        row = args.batch_row[k]  # select_round saw the same velocities: same features, same numbers
        impulse_n = args.batch_out[row, 0]
        impulse_t = args.batch_out[row, 1]
    else:
        write_contact_features(vi, vj, n, 2.0 * ri, 2.0 * rj, rho_i, rho_j, k, features)
        impulse_n = forest_target(forest, 0, features, k)
        impulse_t = forest_target(forest, 1, features, k)
    mi = sphere_mass(2.0 * ri, rho_i)
    mj = sphere_mass(2.0 * rj, rho_j)
    J = contact_impulse(vi, vj, n, mi, mj, impulse_n, impulse_t)  # on j; i gets -J
    wi = args.particle_weight[i]
    wj = args.particle_weight[j]
    w_min = wp.min(wi, wj)
    particle_v[i] = vi - J * (w_min / (wi * mi))
    particle_v[j] = vj + J * (w_min / (wj * mj))
    wp.atomic_add(calls, stream_pair_index(args.particle_stream[i], args.particle_stream[j], args.n_streams), 1)


@wp.kernel
def count_round(more_rounds: wp.array(dtype=wp.int32),
                # outputs
                rounds: wp.array(dtype=wp.int32)):
    rounds[0] = rounds[0] + 1


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
            if wp.length_sq(args.particle_x[j] - xi) < cut * cut:
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


def resolve_pairwise(n_pairs: int, args: PairwiseArgs, forest: Forest, pair_state, features, particle_v, calls,
                     skipped, more_rounds, rounds, batch_forest: Forest | None = None) -> None:
    """Rounds of disjoint pairs until none is pending (``wp.capture_while``: a graph loop on CUDA).

    With ``batch_forest`` (the same model in the perfect layout; ``args.batch_*`` sized to the pairs) the
    pairs a round resolves are first gathered (``select_round``) and predicted in one batched evaluation
    (``eval_forest``: blocks of rows per thread walk each tree together on the CPU, ~3x faster per pair
    than one walk per pair); without it every resolved pair walks the explicit forest inline. Same results."""
    if not n_pairs:
        return
    device = particle_v.device
    n = particle_v.shape[0]
    args.batched = 0 if batch_forest is None else 1
    if batch_forest is not None:
        from kernels.forest import eval_forest

        batch_features, batch_out = args.batch_features[:n_pairs], args.batch_out[:n_pairs]

    def one_round():
        wp.launch(reset_owner, dim=n, device=device, outputs=[args.owner, more_rounds])
        wp.launch(claim_pairs, dim=n_pairs, device=device, inputs=[args.pair_i, args.pair_j, pair_state],
                  outputs=[args.owner])
        if batch_forest is not None:
            args.batch_count.zero_()
            wp.launch(select_round, dim=n_pairs, device=device, inputs=[args, particle_v, pair_state],
                      outputs=[more_rounds])
            eval_forest(batch_forest, batch_features, batch_out, device=device, row_count=args.batch_count)
        wp.launch(resolve_round, dim=n_pairs, device=device, inputs=[args, forest],
                  outputs=[pair_state, features, particle_v, calls, skipped, more_rounds])
        wp.launch(count_round, dim=1, device=device, inputs=[more_rounds], outputs=[rounds])

    more_rounds.fill_(1)
    wp.capture_while(more_rounds, one_round)


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
