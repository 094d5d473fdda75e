"""Flattened tree-ensemble evaluation (the HELSCM surrogate collision model, sec. 4.3).

Node arrays as written by surrogate/flatten.py (format documented there): XGBoost split
semantics (``x < T`` left, NaN -> default direction), thresholds already in raw-feature
space (scaler of eq. 17 folded in), prediction = base_score + sum of leaf values, one tree
group per target, summed in XGBoost's order (base, tree 0, tree 1, ...). Contact form:
features in the contact frame and the equal-and-opposite impulse of surrogate/features.py
``apply_contact_model`` (momentum conserved exactly).

Device layouts (built by hel_warp/collisions/forest.py from the file): 8-byte ``Node`` records
(packed split feature, default direction and child index + threshold or leaf value), either

- ``perfect`` (default when every tree has depth <= 12): each tree padded to a perfect tree
  of its own depth D, level ordered, walked with ``i = 2i + 1 + (x >= T)`` for exactly D
  levels; a leaf above level D is replaced by pass-through nodes whose both subtrees carry
  its value. A CPU thread owns BLOCK_ROWS rows and walks each tree for all of them before
  the next tree (tree-major: the tree stays in L1), LOCKSTEP_ROWS rows side by side (two
  AVX-512 vectors after LLVM's vectorizer); levels 0-2 read their 1, 2 and 4 nodes once and
  pick by selects, deeper levels gather; or
- ``explicit``: breadth-first nodes with child indices, one row at a time, early exit.

Launch wrappers at the bottom; they never allocate (the host side, hel_warp/collisions/forest.py,
owns the scratch arrays).
"""

from __future__ import annotations

import warp as wp

# Forward only; -O3; loops of up to 32 iterations unrolled (the LOCKSTEP_ROWS rows walked side by side);
# on CPU, LLVM may use full-width (AVX-512) vectors for them (its default prefers 256-bit ones); the flag
# is appended to the configured CPU flags.
wp.set_module_options({
    "enable_backward": False,
    "optimization_level": 3,
    "max_unroll": 32,
    "cpu_compiler_flags": (wp.config.cpu_compiler_flags or "-march=native") + " -mprefer-vector-width=512",
})

PAPER_FEATURES = 10  # v1x v1y v1z v2x v2y v2z d1 d2 rho1 rho2
CONTACT_FEATURES = 6  # g_n g_t cos_angle d1 size_ratio density_ratio
TANGENT_EPS = 1.0e-6  # = surrogate.features.TANGENT_EPS: relative slip below which t_hat = 0


NODE_FEATURE_BITS = 4  # features < 16
NODE_CHILD_SHIFT = 1 + NODE_FEATURE_BITS


@wp.struct
class Node:
    """One tree node, 8 bytes (one load per visited node).

    ``meta``: -1 at a leaf; else ``left << 5 | feature << 1 | default_left`` (the right child is
    ``left + 1``). ``value``: leaf value, or the raw-space split threshold T (left iff x < T).
    """

    meta: wp.int32
    value: wp.float32


@wp.struct
class Forest:
    """Flattened forest on the device (file layout: surrogate/flatten.py; packing: hel_warp/collisions/forest.py)."""

    nodes: wp.array(dtype=Node)
    """explicit layout: (n_nodes,) all trees' nodes, breadth first per tree, siblings adjacent;
    perfect layout: each tree's 2^depth - 1 split nodes in level order (children of i: 2i+1, 2i+2)."""
    tree_root: wp.array(dtype=wp.int32)
    """(n_trees,) first node of each tree in ``nodes``."""
    tree_depth: wp.array(dtype=wp.int32)
    """(n_trees,) perfect layout: depth D of each tree (levels walked)."""
    tree_leaf: wp.array(dtype=wp.int32)
    """(n_trees,) perfect layout: first of the tree's 2^D leaf values in ``leaves``."""
    leaves: wp.array(dtype=wp.float32)
    """perfect layout: leaf values, level D of each padded tree, left to right."""
    perfect: wp.int32
    """1: perfect (level-ordered, padded) layout; 0: explicit children."""
    tree_start: wp.array(dtype=wp.int32)
    """(n_targets+1,) trees of target t: tree_start[t] .. tree_start[t+1]-1."""
    base_score: wp.array(dtype=wp.float32)
    """(n_targets,) XGBoost base_score of each target."""
    target_scale: wp.array(dtype=wp.int32)
    """(n_targets,) what the target's tree sum is multiplied by (surrogate/flatten.py ``target_scale``):
    SCALE_NONE, SCALE_COS (the row's cos_angle) or SCALE_SIN (sqrt(1 - cos_angle^2)); contact form only."""


@wp.func
def walk_tree(forest: Forest, root: wp.int32, features: wp.array2d(dtype=wp.float32), row: wp.int32):
    """Leaf value of one tree for one row, EXPLICIT layout: left iff ``x < T``; NaN -> default side."""
    node = forest.nodes[root]
    while node.meta >= 0:
        x = features[row, (node.meta >> 1) & 15]
        # branch-free: a NaN compares false, then takes the default side
        go_right = wp.where(x >= node.value, 1, 0)
        go_right = wp.where(x != x, 1 - (node.meta & 1), go_right)  # x != x: NaN, inlined (wp.isnan is a libm call on CPU)
        node = forest.nodes[(node.meta >> 5) + go_right]
    return node.value


TREE_GROUP = 8
"""Trees one row walks side by side in ``tree_sum`` (independent load chains: a single row's walk is bound by the
latency of its node loads, not by their number)."""
TreeGroup = wp.types.vector(length=TREE_GROUP, dtype=wp.int32)


@wp.func
def tree_sum(forest: Forest, first: wp.int32, last: wp.int32, features: wp.array2d(dtype=wp.float32),
             row: wp.int32, acc: wp.float32):
    """acc + the leaves of trees first .. last - 1 for one row, added in tree order (``walk_tree`` one by one gives
    the same float32 sum), EXPLICIT layout. Groups of TREE_GROUP trees are walked level by level side by side and
    branch-free (a tree at its leaf stays there) until all of the group are at their leaves; the trees after the
    last full group one by one."""
    k = first
    while k + TREE_GROUP <= last:
        node_index = TreeGroup()
        for g in range(TREE_GROUP):
            node_index[g] = forest.tree_root[k + g]
        active = int(1)
        while active != 0:
            active = 0
            for g in range(TREE_GROUP):
                node = forest.nodes[node_index[g]]
                split = node.meta >= 0
                x = features[row, wp.where(split, (node.meta >> 1) & 15, 0)]
                go_right = wp.where(x >= node.value, 1, 0)
                go_right = wp.where(x != x, 1 - (node.meta & 1), go_right)  # NaN: the default side
                node_index[g] = wp.where(split, (node.meta >> 5) + go_right, node_index[g])
                active = active | wp.where(split, 1, 0)
        for g in range(TREE_GROUP):
            acc = acc + forest.nodes[node_index[g]].value
        k = k + TREE_GROUP
    for t in range(k, last):
        acc = acc + walk_tree(forest, forest.tree_root[t], features, row)
    return acc


SCALE_NONE = wp.constant(0)
"""Target scale codes (file names in surrogate/flatten.py TARGET_SCALES): the prediction is the tree sum."""
SCALE_COS = wp.constant(1)
"""The prediction is the tree sum times the row's cos_angle (contact feature COS_FEATURE)."""
SCALE_SIN = wp.constant(2)
"""The prediction is the tree sum times sqrt(1 - cos_angle^2)."""
COS_FEATURE = wp.constant(2)
"""Index of cos_angle among the contact features (CONTACT_FEATURES order)."""


@wp.func
def scale_factor(code: wp.int32, cos_angle: wp.float32):
    """The multiplier of a target's tree sum: 1, cos_angle or sqrt(1 - cos_angle^2) (clamped at 0)."""
    if code == SCALE_COS:
        return cos_angle
    if code == SCALE_SIN:
        return wp.sqrt(wp.max(1.0 - cos_angle * cos_angle, 0.0))
    return 1.0


@wp.func
def perfect_step(forest: Forest, first_node: wp.int32, i: wp.int32, features: wp.array2d(dtype=wp.float32),
                 row: wp.int32):
    """One level of a padded perfect tree: ``i -> 2i + 1 + go_right`` (same split rule as walk_tree)."""
    node = forest.nodes[first_node + i]
    x = features[row, (node.meta >> 1) & 15]
    go_right = wp.where(x >= node.value, 1, 0)
    go_right = wp.where(x != x, 1 - (node.meta & 1), go_right)  # x != x: NaN, inlined (wp.isnan is a libm call on CPU)
    return 2 * i + 1 + go_right


LOCKSTEP_ROWS = 16
"""Rows one thread walks through a perfect-layout tree level by level, side by side (unrolled)."""
BLOCK_GROUPS = 4
"""Lockstep groups per thread: a thread owns BLOCK_GROUPS * LOCKSTEP_ROWS rows and walks each tree
for all of them before the next tree (the tree stays in L1 across the groups)."""
BLOCK_ROWS = BLOCK_GROUPS * LOCKSTEP_ROWS
RowIndex = wp.types.vector(length=LOCKSTEP_ROWS, dtype=wp.int32)
BlockSum = wp.types.vector(length=BLOCK_ROWS, dtype=wp.float32)


@wp.func
def tree_value(forest: Forest, k: wp.int32, features: wp.array2d(dtype=wp.float32), row: wp.int32):
    """Leaf value of tree ``k`` for one row, in either layout (single-row use in other kernels)."""
    if forest.perfect == 0:
        return walk_tree(forest, forest.tree_root[k], features, row)
    i = wp.int32(0)
    for level in range(forest.tree_depth[k]):
        i = perfect_step(forest, forest.tree_root[k], i, features, row)
    return forest.leaves[forest.tree_leaf[k] + i - ((1 << forest.tree_depth[k]) - 1)]


@wp.kernel
def eval_forest_explicit_kernel(forest: Forest, features: wp.array2d(dtype=wp.float32), n_rows: wp.int32,
                                rows_per_thread: wp.int32,
                                # outputs
                                out: wp.array2d(dtype=wp.float32)):
    """Every target for rows [tid*rows_per_thread, ...), EXPLICIT layout: trees outer, rows inner,
    one row at a time with early exit at the leaf; sum base_score + tree 0 + tree 1 + ... (XGBoost's order),
    times the target's scale (``scale_factor``)."""
    tid = wp.tid()
    first = tid * rows_per_thread
    last = wp.min(first + rows_per_thread, n_rows)
    n_targets = forest.tree_start.shape[0] - 1
    for t in range(n_targets):
        base = forest.base_score[t]
        for row in range(first, last):
            out[row, t] = base
        for k in range(forest.tree_start[t], forest.tree_start[t + 1]):
            root = forest.tree_root[k]
            for row in range(first, last):
                out[row, t] = out[row, t] + walk_tree(forest, root, features, row)
        code = forest.target_scale[t]
        if code != SCALE_NONE:
            for row in range(first, last):
                out[row, t] = out[row, t] * scale_factor(code, features[row, COS_FEATURE])


@wp.kernel
def eval_forest_perfect_kernel(forest: Forest, features: wp.array(dtype=wp.float32), n_rows: wp.int32,
                               n_features: wp.int32, row_count: wp.array(dtype=wp.int32),
                               # outputs
                               out: wp.array2d(dtype=wp.float32)):
    """Every target for the BLOCK_ROWS rows [tid*BLOCK_ROWS, ...), PERFECT layout.

    ``features``: the (n_rows, n_features) row-major features, flattened. Tree-major: each tree
    is walked for the whole block (BLOCK_GROUPS groups of LOCKSTEP_ROWS rows side by side, fixed
    trip count, independent loads in flight) before the next tree, so its nodes stay in cache;
    sums kept locally in XGBoost's order base + tree 0 + tree 1 + ..., then times the target's scale. Rows past ``n_rows``
    repeat the last row and are not written. ``row_count`` (optional, on the device): evaluate only the
    first ``min(n_rows, row_count[0])`` rows (a count known only on the device; other blocks return).
    """
    tid = wp.tid()
    first = tid * BLOCK_ROWS
    rows = n_rows
    if row_count.shape[0] > 0:
        rows = wp.min(rows, row_count[0])
    if first >= rows:
        return
    last = wp.min(first + BLOCK_ROWS, rows)
    n_targets = forest.tree_start.shape[0] - 1
    for t in range(n_targets):
        acc = BlockSum()
        base = forest.base_score[t]
        for r in range(BLOCK_ROWS):
            acc[r] = base
        for k in range(forest.tree_start[t], forest.tree_start[t + 1]):
            root = forest.tree_root[k]
            depth = forest.tree_depth[k]
            leaf0 = forest.tree_leaf[k] - ((1 << depth) - 1)
            for g in range(BLOCK_GROUPS):
                if first + g * LOCKSTEP_ROWS >= last:
                    continue  # a block's rows past the batch (a small batch fills one group only)
                row_offset = RowIndex()
                for r in range(LOCKSTEP_ROWS):
                    row_offset[r] = wp.min(first + g * LOCKSTEP_ROWS + r, last - 1) * n_features
                idx = RowIndex()
                if depth > 0:  # level 0: every row at the root (one node load, no gather)
                    node = forest.nodes[root]
                    feature = (node.meta >> 1) & 15
                    nan_right = 1 - (node.meta & 1)
                    for r in range(LOCKSTEP_ROWS):
                        x = features[row_offset[r] + feature]
                        go_right = wp.where(x >= node.value, 1, 0)
                        go_right = wp.where(x != x, nan_right, go_right)  # NaN: default side
                        idx[r] = 1 + go_right
                if depth > 1:  # level 1: node 1 or 2, picked by a select
                    left = forest.nodes[root + 1]
                    right = forest.nodes[root + 2]
                    for r in range(LOCKSTEP_ROWS):
                        meta = wp.where(idx[r] == 2, right.meta, left.meta)
                        threshold = wp.where(idx[r] == 2, right.value, left.value)
                        x = features[row_offset[r] + ((meta >> 1) & 15)]
                        go_right = wp.where(x >= threshold, 1, 0)
                        go_right = wp.where(x != x, 1 - (meta & 1), go_right)  # NaN: default side
                        idx[r] = 2 * idx[r] + 1 + go_right
                if depth > 2:  # level 2: nodes 3..6, picked by selects
                    n3 = forest.nodes[root + 3]
                    n4 = forest.nodes[root + 4]
                    n5 = forest.nodes[root + 5]
                    n6 = forest.nodes[root + 6]
                    for r in range(LOCKSTEP_ROWS):
                        meta = wp.where(idx[r] >= 5, wp.where(idx[r] == 6, n6.meta, n5.meta),
                                        wp.where(idx[r] == 4, n4.meta, n3.meta))
                        threshold = wp.where(idx[r] >= 5, wp.where(idx[r] == 6, n6.value, n5.value),
                                             wp.where(idx[r] == 4, n4.value, n3.value))
                        x = features[row_offset[r] + ((meta >> 1) & 15)]
                        go_right = wp.where(x >= threshold, 1, 0)
                        go_right = wp.where(x != x, 1 - (meta & 1), go_right)  # NaN: default side
                        idx[r] = 2 * idx[r] + 1 + go_right
                for level in range(3, depth):
                    for r in range(LOCKSTEP_ROWS):
                        node = forest.nodes[root + idx[r]]
                        x = features[row_offset[r] + ((node.meta >> 1) & 15)]
                        go_right = wp.where(x >= node.value, 1, 0)
                        go_right = wp.where(x != x, 1 - (node.meta & 1), go_right)  # NaN: default side
                        idx[r] = 2 * idx[r] + 1 + go_right
                for r in range(LOCKSTEP_ROWS):
                    acc[g * LOCKSTEP_ROWS + r] = acc[g * LOCKSTEP_ROWS + r] + forest.leaves[leaf0 + idx[r]]
        code = forest.target_scale[t]
        if code != SCALE_NONE:
            for r in range(last - first):
                acc[r] = acc[r] * scale_factor(code, features[(first + r) * n_features + COS_FEATURE])
        for r in range(last - first):
            out[first + r, t] = acc[r]


@wp.kernel
def eval_forest_perfect_rows_kernel(forest: Forest, features: wp.array(dtype=wp.float32), n_rows: wp.int32,
                                    n_features: wp.int32, row_count: wp.array(dtype=wp.int32),
                                    # outputs
                                    out: wp.array2d(dtype=wp.float32)):
    """``eval_forest_perfect_kernel``'s numbers with one thread per (row, target) (launch n_rows * n_targets
    threads; thread ``row * n_targets + t``): the GPU's form. ``eval_forest_perfect_kernel`` gives a thread
    BLOCK_ROWS rows and every tree, the CPU's best form, which on a GPU leaves ~30 threads for a batch of 2,000 rows
    (measured on an H200: ~1.4 ms per batch whatever its size, 19 of the cooling box's 23 ms of device time per
    step; this kernel ~67 us per batch there). Here TREE_GROUP trees are walked side by side (independent load chains; a tree stops at its own depth),
    their leaves then added one by one in tree order: base + tree 0 + tree 1 + ... in float32 as the block kernel
    adds them, so both give the same bits. ``row_count`` as there."""
    tid = wp.tid()
    n_targets = forest.tree_start.shape[0] - 1
    row = tid / n_targets
    t = tid - row * n_targets
    rows = n_rows
    if row_count.shape[0] > 0:
        rows = wp.min(rows, row_count[0])
    if row >= rows:
        return
    offset = row * n_features
    acc = forest.base_score[t]
    k = forest.tree_start[t]
    last = forest.tree_start[t + 1]
    while k <= last - TREE_GROUP:
        idx = TreeGroup()
        depth = TreeGroup()
        root = TreeGroup()
        deepest = int(0)
        for g in range(TREE_GROUP):
            depth[g] = forest.tree_depth[k + g]
            root[g] = forest.tree_root[k + g]
            deepest = wp.max(deepest, depth[g])
        for level in range(deepest):
            for g in range(TREE_GROUP):
                if level < depth[g]:
                    node = forest.nodes[root[g] + idx[g]]
                    x = features[offset + ((node.meta >> 1) & 15)]
                    go_right = wp.where(x >= node.value, 1, 0)
                    go_right = wp.where(x != x, 1 - (node.meta & 1), go_right)  # NaN: default side
                    idx[g] = 2 * idx[g] + 1 + go_right
        for g in range(TREE_GROUP):
            acc = acc + forest.leaves[forest.tree_leaf[k + g] + idx[g] - ((1 << depth[g]) - 1)]
        k = k + TREE_GROUP
    while k < last:
        i = int(0)
        depth_k = forest.tree_depth[k]
        for level in range(depth_k):
            node = forest.nodes[forest.tree_root[k] + i]
            x = features[offset + ((node.meta >> 1) & 15)]
            go_right = wp.where(x >= node.value, 1, 0)
            go_right = wp.where(x != x, 1 - (node.meta & 1), go_right)  # NaN: default side
            i = 2 * i + 1 + go_right
        acc = acc + forest.leaves[forest.tree_leaf[k] + i - ((1 << depth_k) - 1)]
        k = k + 1
    code = forest.target_scale[t]
    if code != SCALE_NONE:
        acc = acc * scale_factor(code, features[offset + COS_FEATURE])
    out[row, t] = acc


@wp.func
def tangent_direction(g: wp.vec3, n: wp.vec3):
    """Unit slip direction of ``g`` in the contact plane (two Gram-Schmidt passes), zero if none."""
    gt = g - wp.dot(g, n) * n
    gt = gt - wp.dot(gt, n) * n
    gt_mag = wp.length(gt)
    if gt_mag > TANGENT_EPS * wp.length(g):
        return gt / gt_mag
    return wp.vec3(0.0)


@wp.func
def sphere_mass(d: wp.float32, rho: wp.float32):
    """rho pi d^3 / 6."""
    return rho * (wp.pi / 6.0) * d * d * d


@wp.func
def contact_impulse(v1: wp.vec3, v2: wp.vec3, n: wp.vec3, m1: wp.float32, m2: wp.float32,
                    impulse_n: wp.float32, impulse_t: wp.float32):
    """Impulse on particle 2, ``J = m*|g| (impulse_n n + impulse_t t_hat)``; particle 1 gets -J."""
    g = v1 - v2
    m_eff = m1 * m2 / (m1 + m2)
    return m_eff * wp.length(g) * (impulse_n * n + impulse_t * tangent_direction(g, n))


# ------------------------------------------------------------------ training domain and admissibility

GUARD_SEPARATION, GUARD_COULOMB, GUARD_ENERGY = 1, 2, 4
"""``admissible_impulse`` flag bits: a raised to c (not separating), b lowered to the Coulomb bound,
the post-collision relative speed brought back to |g| (energy)."""
ENERGY_RADIUS = 0.999999
"""|g'|/|g| the energy correction aims at: just inside 1, so the float32 rounding of the post-collision
velocities cannot carry the outcome above the pre-collision kinetic energy."""


DOMAIN_ROUNDOFF = 4.8e-7
"""Relative slack (4 float32 ulps) of the domain test: the kernel's own rounding of a training pair
(e.g. ``g_n/|g| = 1.0000001`` for a central impact) is not an excursion out of the domain."""


@wp.struct
class ContactDomain:
    """Training domain of a contact-form model (``FlatForest.domain_to_device``; file: surrogate/flatten.py)."""

    feature_lo: wp.array(dtype=wp.float32)
    """(6,) canonical contact features g_n, g_t, cos_angle, d1, size_ratio, density_ratio: training minimum."""
    feature_hi: wp.array(dtype=wp.float32)
    """(6,) training maximum."""
    friction_bound: wp.float32
    """Coulomb guard: normalised tangential impulse b <= friction_bound * a (chosen from the DEM data)."""
    separation_slack: wp.float32
    """Separation guard: the normalised normal impulse a may fall short of cos_angle by this much (a >= c - slack):
    the largest shortfall the training DEM itself shows at grazing incidence, where the soft contact turns the
    centre line while the spheres slide; 0 is the strict rule."""


@wp.func
def contact_pair_features(v1: wp.vec3, v2: wp.vec3, n: wp.vec3, d1: float, d2: float, rho1: float, rho2: float):
    """The 6 canonical contact features, raw (surrogate/features.py ``raw_features``), as a vector."""
    g = v1 - v2
    g_n = wp.dot(g, n)
    gt = g - g_n * n
    gt = gt - wp.dot(gt, n) * n
    return wp.types.vector(g_n, wp.length(gt), g_n / wp.length(g), d1, d2 / d1, rho2 / rho1, length=6,
                           dtype=wp.float32)


@wp.func
def write_contact_features_in_domain(v1: wp.vec3, v2: wp.vec3, n: wp.vec3, d1: float, d2: float, rho1: float,
                                     rho2: float, domain: ContactDomain, row: int,
                                     # outputs
                                     features: wp.array2d(dtype=wp.float32)) -> int:
    """Write the 6 canonical features of the pair into ``features[row]``, clamped into ``domain``.

    ``n``: unit normal from 1 to 2, the pair approaching, ``(v1 - v2).n > 0``. Inside the domain the
    features are written exactly as ``contact_features_kernel`` computes them. Outside, consistently:
    the incidence ``cos_angle`` is clamped first, then ``|g|`` is scaled (the same factor on g_n and
    g_t, so the clamped ``g_n/|g|`` is kept) into the range where both ``g_n = |g| c`` and
    ``g_t = |g| sqrt(1 - c^2)`` lie in their training ranges; d1 and the two ratios are clamped on
    their own. The outcome is a normalised impulse (units m*|g|), applied with the pair's own |g|.
    A feature within DOMAIN_ROUNDOFF of a bound counts as inside. Returns 1 when anything was
    clamped, else 0.
    """
    raw = contact_pair_features(v1, v2, n, d1, d2, rho1, rho2)
    outside = int(0)
    kinematic = int(0)
    for k in range(6):
        lo = domain.feature_lo[k]
        hi = domain.feature_hi[k]
        if not (raw[k] >= lo - DOMAIN_ROUNDOFF * wp.abs(lo) and raw[k] <= hi + DOMAIN_ROUNDOFF * wp.abs(hi)):
            outside = 1
            if k < 3:
                kinematic = 1
    if kinematic == 1:
        g_mag = wp.sqrt(raw[0] * raw[0] + raw[1] * raw[1])
        c = wp.clamp(raw[2], domain.feature_lo[2], domain.feature_hi[2])
        s = wp.sqrt(wp.max(1.0 - c * c, 0.0))
        g_lo = float(0.0)
        g_hi = float(3.0e38)
        if c > 0.0:
            g_lo = wp.max(g_lo, domain.feature_lo[0] / c)
            g_hi = wp.min(g_hi, domain.feature_hi[0] / c)
        if s > 0.0:
            g_lo = wp.max(g_lo, domain.feature_lo[1] / s)
            g_hi = wp.min(g_hi, domain.feature_hi[1] / s)
        g_new = wp.min(wp.max(g_mag, g_lo), g_hi)
        raw[0] = wp.clamp(g_new * c, domain.feature_lo[0], domain.feature_hi[0])
        raw[1] = wp.clamp(g_new * s, domain.feature_lo[1], domain.feature_hi[1])
        raw[2] = c
    if outside == 1:
        for k in range(3, 6):
            raw[k] = wp.clamp(raw[k], domain.feature_lo[k], domain.feature_hi[k])
    for k in range(6):
        features[row, k] = raw[k]
    return outside


@wp.func
def admissible_impulse(cos_angle: float, impulse_n: float, impulse_t: float, friction_bound: float,
                       separation_slack: float):
    """Normalised impulse on particle 2 ``(a, b)`` along ``n`` and ``t_hat`` (units m*|g|, as
    ``contact_impulse``) corrected into the admissible set; returns ``(a, b, flags)``.

    With ``c = cos_angle`` (the pair's own, not clamped), ``s = sqrt(1 - c^2)``, the post-collision
    relative velocity is ``g' = |g| ((c - a) n + (s - b) t_hat)`` (docs/physics/references.md "Binary collision
    outcome"), so in ``u = g'/|g|``:

    - flag 1 (GUARD_SEPARATION): separating along n, ``u_n = c - a <= separation_slack``: ``a`` raised to
      ``c - separation_slack`` (0: strictly separating along the first-touch normal; the engine passes the largest
      shortfall of the training DEM, whose grazing contacts end with the centre line turned);
    - flag 2 (GUARD_COULOMB): ``b <= friction_bound * a``: ``b`` lowered to the bound;
    - flag 4 (GUARD_ENERGY): ``|u| <= 1`` (an internal impulse leaves the centre-of-mass energy
      unchanged, so this is "kinetic energy never grows"): ``u`` projected onto the disc of radius
      ENERGY_RADIUS (the direction of g' kept); if that breaks the Coulomb bound, ``u`` moves
      instead along the segment towards ``(0, s)`` (a = c, b = 0, which satisfies all three) to the
      circle. Both keep flags 1 and 2 satisfied (convex set).

    NaN predictions are corrected too (a NaN fails every test). ``flags`` = OR of the corrections made.
    """
    c = wp.clamp(cos_angle, 0.0, 1.0)
    s = wp.sqrt(wp.max(1.0 - c * c, 0.0))
    a = impulse_n
    b = impulse_t
    flags = int(0)
    a_min = c - separation_slack
    if not (a >= a_min):
        a = a_min
        flags = flags | GUARD_SEPARATION
    b_max = friction_bound * a
    if not (b <= b_max):
        b = b_max
        flags = flags | GUARD_COULOMB
    u_n = c - a
    u_t = s - b
    u2 = u_n * u_n + u_t * u_t
    if u2 > 1.0:
        flags = flags | GUARD_ENERGY
        scale = ENERGY_RADIUS / wp.sqrt(u2)
        p_n = u_n * scale
        p_t = u_t * scale
        if s - p_t <= friction_bound * (c - p_n):
            u_n = p_n
            u_t = p_t
        else:
            # u(m) = u0 + m (u - u0), u0 = (0, s): |u(m)| = ENERGY_RADIUS, m in [0, 1]
            w_n = u_n
            w_t = u_t - s
            ww = w_n * w_n + w_t * w_t
            uw = s * w_t
            disc = uw * uw - ww * (s * s - ENERGY_RADIUS * ENERGY_RADIUS)
            m = float(0.0)
            if ww > 0.0 and disc > 0.0:
                m = wp.clamp((-uw + wp.sqrt(disc)) / ww, 0.0, 1.0)
            u_n = m * w_n
            u_t = s + m * w_t
        a = wp.max(c - u_n, a_min)
        b = s - u_t
    return a, b, flags


SPIN_ENERGY_FACTOR = 3.5
"""``m* (1/m1 + 1/m2 + r1^2/I1 + r2^2/I2)`` of two solid spheres (I = 2/5 m r^2): the inverse effective mass of the
contact point's tangential motion in units of 1/m*, whatever the sizes and densities (docs/physics/spin-and-mixtures.md "Spin in
particle-particle collisions")."""


@wp.func
def contact_point_velocity(v: wp.vec3, omega: wp.vec3, r: float, n: wp.vec3):
    """Velocity of a sphere's surface point at ``r n`` from its centre: ``v + omega x (r n)`` (``n`` from 1 to 2
    for sphere 1, ``-n`` for sphere 2)."""
    return v + r * wp.cross(omega, n)


@wp.func
def spin_kick(impulse: wp.vec3, n: wp.vec3, r: float, mass: float):
    """Spin change of either sphere of a pair from the contact impulse ``impulse`` on sphere 2 (sphere 1 gets its
    opposite), ``n`` from 1 to 2: sphere 1's torque is ``(r1 n) x (-J)``, sphere 2's ``(-r2 n) x J``; both are
    ``-r n x J``, divided by ``I = 2/5 m r^2``."""
    return wp.cross(n, impulse) * (-1.0 / (0.4 * mass * r))


@wp.func
def spin_energy_guard(cos_angle: float, impulse_n: float, impulse_t: float, impulse_b: float):
    """The total kinetic energy (translation and spin) never grows: returns ``(a, b, c, flag)``.

    An impulse ``J = m*|g_c| (a n + b t_hat + c b_hat)`` through the contact point (``g_c`` the contact points'
    relative velocity, ``cl = g_c.n/|g_c|``, ``s`` its sine; g_c has no part along b_hat) changes the pair's energy
    by ``m*|g_c|^2 ((a^2 + K (b^2 + c^2))/2 - a cl - b s)``, K = SPIN_ENERGY_FACTOR. Where that is positive the
    outcome moves along the segment towards ``(cl, 0, 0)`` (the contact points stop along n and keep their slip:
    energy change ``-cl^2/2 <= 0``, separating, inside every Coulomb cone) to where it is zero, flag GUARD_ENERGY.
    The separation and Coulomb bounds are linear in ``(a, b, c)`` and hold at both ends of the segment, so a point
    that met them before meets them after. Stricter than ``admissible_impulse``'s translational bound ``|u| <= 1``
    (K = 1), which it follows."""
    cl = wp.clamp(cos_angle, 0.0, 1.0)
    s = wp.sqrt(wp.max(1.0 - cl * cl, 0.0))
    a = impulse_n
    b = impulse_t
    c = impulse_b
    k = float(SPIN_ENERGY_FACTOR)
    if a * a + k * (b * b + c * c) <= 2.0 * (a * cl + b * s):
        return a, b, c, int(0)
    # (a, b, c)(m) = (cl, 0, 0) + m (a - cl, b, c): energy change -cl^2/2 + m^2 q/2 - m b s, q = (a-cl)^2 + K (b^2+c^2)
    da = a - cl
    q = da * da + k * (b * b + c * c)
    m = float(0.0)
    if q > 0.0:
        m = wp.clamp((b * s + wp.sqrt(b * b * s * s + q * cl * cl)) / q, 0.0, 1.0)
    return cl + m * da, m * b, m * c, int(GUARD_ENERGY)


@wp.kernel
def contact_features_in_domain_kernel(v1: wp.array(dtype=wp.vec3), v2: wp.array(dtype=wp.vec3),
                                      n: wp.array(dtype=wp.vec3), d1: wp.array(dtype=wp.float32),
                                      d2: wp.array(dtype=wp.float32), rho1: wp.array(dtype=wp.float32),
                                      rho2: wp.array(dtype=wp.float32), domain: ContactDomain,
                                      # outputs
                                      features: wp.array2d(dtype=wp.float32), clamped: wp.array(dtype=wp.int32)):
    """Features of each pair clamped into the training domain; ``clamped[0]`` += pairs clamped (int atomics)."""
    i = wp.tid()
    if write_contact_features_in_domain(v1[i], v2[i], n[i], d1[i], d2[i], rho1[i], rho2[i], domain, i,
                                        features) == 1:
        wp.atomic_add(clamped, 0, 1)


@wp.kernel
def apply_admissible_contact_kernel(v1: wp.array(dtype=wp.vec3), v2: wp.array(dtype=wp.vec3),
                                    n: wp.array(dtype=wp.vec3), d1: wp.array(dtype=wp.float32),
                                    d2: wp.array(dtype=wp.float32), rho1: wp.array(dtype=wp.float32),
                                    rho2: wp.array(dtype=wp.float32), targets: wp.array2d(dtype=wp.float32),
                                    friction_bound: wp.float32, separation_slack: wp.float32,
                                    # outputs
                                    v1_after: wp.array(dtype=wp.vec3), v2_after: wp.array(dtype=wp.vec3),
                                    guard_counts: wp.array(dtype=wp.int32)):
    """Equal and opposite impulse of the guarded targets (``admissible_impulse`` with the pair's own
    incidence); ``guard_counts`` += [flag 1, flag 2, flag 4, any] corrections (int atomics)."""
    i = wp.tid()
    g = v1[i] - v2[i]
    a, b, flags = admissible_impulse(wp.dot(g, n[i]) / wp.length(g), targets[i, 0], targets[i, 1], friction_bound,
                                     separation_slack)
    m1 = sphere_mass(d1[i], rho1[i])
    m2 = sphere_mass(d2[i], rho2[i])
    J = contact_impulse(v1[i], v2[i], n[i], m1, m2, a, b)
    v1_after[i] = v1[i] - J / m1
    v2_after[i] = v2[i] + J / m2
    if flags & GUARD_SEPARATION:
        wp.atomic_add(guard_counts, 0, 1)
    if flags & GUARD_COULOMB:
        wp.atomic_add(guard_counts, 1, 1)
    if flags & GUARD_ENERGY:
        wp.atomic_add(guard_counts, 2, 1)
    if flags != 0:
        wp.atomic_add(guard_counts, 3, 1)


@wp.func
def contact_spin_frame(v1: wp.vec3, v2: wp.vec3, c1: wp.vec3, c2: wp.vec3, n: wp.vec3):
    """The contact_spin frame (surrogate/features.py ``contact_spin_frame``, its numpy twin) from the centres'
    velocities ``v1, v2`` and the contact points' ``c1, c2``: returns ``(t_hat, b_hat, gc_mag, u_along,
    u_across)``; ``t_hat`` the slip direction of g_c = c1 - c2 (else the translational slip's, else 0)."""
    g = v1 - v2
    gc = c1 - c2
    g_n = wp.dot(g, n)
    s = gc - wp.dot(gc, n) * n
    s = s - wp.dot(s, n) * n
    u = g - g_n * n
    u = u - wp.dot(u, n) * n
    slip = wp.length(s)
    gc_mag = wp.sqrt(g_n * g_n + slip * slip)
    u_mag = wp.length(u)
    t_hat = wp.vec3(0.0)
    if slip > TANGENT_EPS * gc_mag:
        t_hat = s / slip
    elif u_mag > TANGENT_EPS * wp.max(gc_mag, u_mag):
        t_hat = u / u_mag
    u_along = wp.dot(u, t_hat)
    rest = u - u_along * t_hat
    u_across = wp.length(rest)
    b_hat = wp.vec3(0.0)
    if u_across > TANGENT_EPS * wp.max(gc_mag, u_mag):
        b_hat = rest / u_across
    else:
        u_across = 0.0
    return t_hat, b_hat, gc_mag, u_along, u_across


@wp.func
def write_contact_spin_features_in_domain(v1: wp.vec3, v2: wp.vec3, c1: wp.vec3, c2: wp.vec3, n: wp.vec3,
                                          d1: float, d2: float, rho1: float, rho2: float, domain: ContactDomain,
                                          row: int,
                                          # outputs
                                          features: wp.array2d(dtype=wp.float32)) -> int:
    """The 8 contact_spin features of the pair into ``features[row]``, clamped into ``domain``: the first six are
    the contact form's of the contact points' velocities (``write_contact_features_in_domain(c1, c2, ...)``: g_n,
    the slip, g_n/|g_c|, sizes, densities), then u_along and u_across (each clamped to its range). Returns 1 when
    anything was clamped."""
    outside = write_contact_features_in_domain(c1, c2, n, d1, d2, rho1, rho2, domain, row, features)
    t_hat, b_hat, gc_mag, u_along, u_across = contact_spin_frame(v1, v2, c1, c2, n)
    extra = wp.vec2(u_along, u_across)
    for k in range(2):
        lo = domain.feature_lo[6 + k]
        hi = domain.feature_hi[6 + k]
        x = extra[k]
        if not (x >= lo - DOMAIN_ROUNDOFF * wp.abs(lo) and x <= hi + DOMAIN_ROUNDOFF * wp.abs(hi)):
            outside = 1
            x = wp.clamp(x, lo, hi)
        features[row, 6 + k] = x
    return outside


@wp.func
def contact_spin_impulse(v1: wp.vec3, v2: wp.vec3, c1: wp.vec3, c2: wp.vec3, n: wp.vec3, m1: float, m2: float,
                         impulse_n: float, impulse_t: float, impulse_b: float):
    """Impulse on particle 2 of the contact_spin form, ``J = m*|g_c| (impulse_n n + impulse_t t_hat + impulse_b
    b_hat)`` (``contact_spin_frame``); particle 1 gets -J."""
    t_hat, b_hat, gc_mag, u_along, u_across = contact_spin_frame(v1, v2, c1, c2, n)
    m_eff = m1 * m2 / (m1 + m2)
    return m_eff * gc_mag * (impulse_n * n + impulse_t * t_hat + impulse_b * b_hat)


@wp.func
def pair_energy_change(v1: wp.vec3, v2: wp.vec3, v1_new: wp.vec3, v2_new: wp.vec3, w1: wp.vec3, w2: wp.vec3,
                       w1_new: wp.vec3, w2_new: wp.vec3, r1: float, r2: float, m1: float, m2: float, weight1: float,
                       weight2: float):
    """Change of the kinetic energy with rotation of two parcels (I = 2/5 m r^2 per particle, ``weight`` particles
    each) and the energy before in their centre-of-mass frame, ``(dE, E_rel)``, J. Written from the increments in
    that frame (``M (v - v_cm).dv + M |dv|^2 / 2``) so that its round-off scales with the collision's energy, not
    with the mean flow's."""
    M1 = weight1 * m1
    M2 = weight2 * m2
    v_cm = (M1 * v1 + M2 * v2) / (M1 + M2)
    a1 = v1 - v_cm
    a2 = v2 - v_cm
    d1 = v1_new - v1
    d2 = v2_new - v2
    I1 = 0.4 * M1 * r1 * r1
    I2 = 0.4 * M2 * r2 * r2
    e1 = w1_new - w1
    e2 = w2_new - w2
    change = M1 * (wp.dot(a1, d1) + 0.5 * wp.dot(d1, d1)) + M2 * (wp.dot(a2, d2) + 0.5 * wp.dot(d2, d2))
    change += I1 * (wp.dot(w1, e1) + 0.5 * wp.dot(e1, e1)) + I2 * (wp.dot(w2, e2) + 0.5 * wp.dot(e2, e2))
    before = 0.5 * (M1 * wp.dot(a1, a1) + M2 * wp.dot(a2, a2) + I1 * wp.dot(w1, w1) + I2 * wp.dot(w2, w2))
    return change, before


@wp.func
def turn_spins(v1: wp.vec3, v2: wp.vec3, v1_new: wp.vec3, v2_new: wp.vec3, w1: wp.vec3, w2: wp.vec3, n: wp.vec3,
               r1: float, r2: float, m1: float, m2: float, weight1: float, weight2: float, share1: float,
               share2: float, impulse: wp.vec3, impulse_rot: wp.vec3):
    """The spins after a collision whose impulse ``impulse`` (on 2) moved the centres to ``v1_new, v2_new``:
    ``omega_k -= share_k r_k n x J_rot / I_k`` (``spin_kick``; ``share_k`` = w_min / weight_k) with the moment
    impulse ``impulse_rot`` of a contact_spin model (the spins' own target); where that would leave the pair with
    more kinetic energy (translation and rotation, ``pair_energy_change``) than before, the impulse's own
    tangential part (``J_rot = J``, the rigid lever, which the spin guard bounded) instead. Returns
    ``(w1', w2', fell_back)``."""
    w1_new = w1 + spin_kick(impulse_rot, n, r1, m1) * share1
    w2_new = w2 + spin_kick(impulse_rot, n, r2, m2) * share2
    change, before = pair_energy_change(v1, v2, v1_new, v2_new, w1, w2, w1_new, w2_new, r1, r2, m1, m2, weight1,
                                        weight2)
    fell_back = int(0)
    if not (change <= 1.0e-6 * before):
        w1_new = w1 + spin_kick(impulse, n, r1, m1) * share1
        w2_new = w2 + spin_kick(impulse, n, r2, m2) * share2
        fell_back = 1
    return w1_new, w2_new, fell_back


@wp.func
def spin_guard(cos_angle: float, impulse_n: float, impulse_t: float, impulse_b: float, friction_bound: float,
               separation_slack: float, rotation: int):
    """The admissibility guard of a contact_spin (or spinning contact) outcome ``(a, b, c)``: ``admissible_impulse``
    on ``(a, b)``, the Coulomb bound on ``|(b, c)| <= friction_bound a`` (both scaled), and with ``rotation`` (the
    impulse turns the spins) the total-energy bound ``spin_energy_guard`` (along the segment towards the outcome
    that stops the contact points along n, which keeps the other two bounds). Returns ``(a, b, c, flags)``."""
    a, b, flags = admissible_impulse(cos_angle, impulse_n, impulse_t, friction_bound, separation_slack)
    c = impulse_b
    if not (c == c):
        c = 0.0
        flags = flags | GUARD_COULOMB
    tangential = wp.sqrt(b * b + c * c)
    cap = friction_bound * a
    if tangential > cap and tangential > 0.0:
        scale = wp.max(cap, 0.0) / tangential
        b = b * scale
        c = c * scale
        flags = flags | GUARD_COULOMB
    if rotation != 0:
        k = float(SPIN_ENERGY_FACTOR)
        cl = wp.clamp(cos_angle, 0.0, 1.0)
        sn = wp.sqrt(wp.max(1.0 - cl * cl, 0.0))
        if a * a + k * (b * b + c * c) > 2.0 * (a * cl + b * sn):
            a, b, c, spin_flag = spin_energy_guard(cos_angle, a, b, c)
            flags = flags | GUARD_ENERGY | spin_flag
    return a, b, c, flags


@wp.kernel
def contact_point_velocities_kernel(v1: wp.array(dtype=wp.vec3), v2: wp.array(dtype=wp.vec3),
                                    omega1: wp.array(dtype=wp.vec3), omega2: wp.array(dtype=wp.vec3),
                                    n: wp.array(dtype=wp.vec3), d1: wp.array(dtype=wp.float32),
                                    d2: wp.array(dtype=wp.float32),
                                    # outputs
                                    c1: wp.array(dtype=wp.vec3), c2: wp.array(dtype=wp.vec3)):
    """The contact points' velocities of spinning pairs (``contact_point_velocity``; n from 1 to 2)."""
    i = wp.tid()
    c1[i] = contact_point_velocity(v1[i], omega1[i], 0.5 * d1[i], n[i])
    c2[i] = contact_point_velocity(v2[i], omega2[i], 0.5 * d2[i], -n[i])


@wp.kernel
def contact_spin_features_in_domain_kernel(v1: wp.array(dtype=wp.vec3), v2: wp.array(dtype=wp.vec3),
                                           c1: wp.array(dtype=wp.vec3), c2: wp.array(dtype=wp.vec3),
                                           n: wp.array(dtype=wp.vec3), d1: wp.array(dtype=wp.float32),
                                           d2: wp.array(dtype=wp.float32), rho1: wp.array(dtype=wp.float32),
                                           rho2: wp.array(dtype=wp.float32), domain: ContactDomain,
                                           # outputs
                                           features: wp.array2d(dtype=wp.float32), clamped: wp.array(dtype=wp.int32)):
    """``write_contact_spin_features_in_domain`` of each pair; ``clamped[0]`` += pairs clamped."""
    i = wp.tid()
    if write_contact_spin_features_in_domain(v1[i], v2[i], c1[i], c2[i], n[i], d1[i], d2[i], rho1[i], rho2[i], domain,
                                             i, features) == 1:
        wp.atomic_add(clamped, 0, 1)


@wp.kernel
def apply_admissible_contact_spin_kernel(v1: wp.array(dtype=wp.vec3), v2: wp.array(dtype=wp.vec3),
                                         omega1: wp.array(dtype=wp.vec3), omega2: wp.array(dtype=wp.vec3),
                                         n: wp.array(dtype=wp.vec3), d1: wp.array(dtype=wp.float32),
                                         d2: wp.array(dtype=wp.float32), rho1: wp.array(dtype=wp.float32),
                                         rho2: wp.array(dtype=wp.float32), targets: wp.array2d(dtype=wp.float32),
                                         friction_bound: wp.float32, separation_slack: wp.float32,
                                         rotation: int, use_guard: int,
                                         # outputs
                                         v1_after: wp.array(dtype=wp.vec3), v2_after: wp.array(dtype=wp.vec3),
                                         omega1_after: wp.array(dtype=wp.vec3), omega2_after: wp.array(dtype=wp.vec3),
                                         guard_counts: wp.array(dtype=wp.int32)):
    """``apply_admissible_contact_kernel`` for spinning spheres: the targets are those of the contact points'
    relative velocity g_c (features from ``contact_point_velocities_kernel``); with ``rotation`` (the engine's
    particle_spin) the guard adds the total-energy bound (``spin_energy_guard``) and the impulse turns the spins
    through the contact point (``spin_kick``); without, the spins stay (a contact_spin model in a spinless run).
    ``use_guard`` 0: the bare targets (measuring the raw model)."""
    i = wp.tid()
    r1 = 0.5 * d1[i]
    r2 = 0.5 * d2[i]
    c1 = contact_point_velocity(v1[i], omega1[i], r1, n[i])
    c2 = contact_point_velocity(v2[i], omega2[i], r2, -n[i])
    g = c1 - c2
    cos_angle = wp.dot(g, n[i]) / wp.length(g)
    impulse_b = float(0.0)
    if targets.shape[1] > 2:
        impulse_b = targets[i, 2]
    a = targets[i, 0]
    b = targets[i, 1]
    c = impulse_b
    flags = int(0)
    if use_guard != 0:
        a, b, c, flags = spin_guard(cos_angle, a, b, c, friction_bound, separation_slack, rotation)
    m1 = sphere_mass(d1[i], rho1[i])
    m2 = sphere_mass(d2[i], rho2[i])
    J = contact_spin_impulse(v1[i], v2[i], c1, c2, n[i], m1, m2, a, b, c)
    u1 = v1[i] - J / m1
    u2 = v2[i] + J / m2
    J_rot = J
    if targets.shape[1] > 4:  # a contact_spin model's moment impulse
        J_rot = contact_spin_impulse(v1[i], v2[i], c1, c2, n[i], m1, m2, 0.0, targets[i, 3], targets[i, 4])
    o1 = omega1[i]
    o2 = omega2[i]
    if rotation != 0:
        fell_back = int(0)
        o1, o2, fell_back = turn_spins(v1[i], v2[i], u1, u2, omega1[i], omega2[i], n[i], r1, r2, m1, m2, 1.0, 1.0,
                                       1.0, 1.0, J, J_rot)
        if fell_back != 0:
            flags = flags | GUARD_ENERGY
    v1_after[i] = u1
    v2_after[i] = u2
    omega1_after[i] = o1
    omega2_after[i] = o2
    if flags & GUARD_SEPARATION:
        wp.atomic_add(guard_counts, 0, 1)
    if flags & GUARD_COULOMB:
        wp.atomic_add(guard_counts, 1, 1)
    if flags & GUARD_ENERGY:
        wp.atomic_add(guard_counts, 2, 1)
    if flags != 0:
        wp.atomic_add(guard_counts, 3, 1)


@wp.kernel
def admissible_targets_kernel(cos_angle: wp.array(dtype=wp.float32), targets: wp.array2d(dtype=wp.float32),
                              friction_bound: wp.float32, separation_slack: wp.float32,
                              # outputs
                              guarded: wp.array2d(dtype=wp.float32), flags: wp.array(dtype=wp.int32)):
    """``admissible_impulse`` row by row (metrics and tests: the corrected targets and the flags of each row)."""
    i = wp.tid()
    a, b, f = admissible_impulse(cos_angle[i], targets[i, 0], targets[i, 1], friction_bound, separation_slack)
    guarded[i, 0] = a
    guarded[i, 1] = b
    flags[i] = f


@wp.kernel
def contact_features_kernel(v1: wp.array(dtype=wp.vec3), v2: wp.array(dtype=wp.vec3), n: wp.array(dtype=wp.vec3),
                            d1: wp.array(dtype=wp.float32), d2: wp.array(dtype=wp.float32),
                            rho1: wp.array(dtype=wp.float32), rho2: wp.array(dtype=wp.float32),
                            # outputs
                            features: wp.array2d(dtype=wp.float32)):
    """Contact-frame features g_n, g_t, g_n/|g|, d1, d2/d1, rho2/rho1 of each pair (n from 1 to 2)."""
    i = wp.tid()
    g = v1[i] - v2[i]
    g_n = wp.dot(g, n[i])
    gt = g - g_n * n[i]
    gt = gt - wp.dot(gt, n[i]) * n[i]
    features[i, 0] = g_n
    features[i, 1] = wp.length(gt)
    features[i, 2] = g_n / wp.length(g)
    features[i, 3] = d1[i]
    features[i, 4] = d2[i] / d1[i]
    features[i, 5] = rho2[i] / rho1[i]


@wp.kernel
def apply_contact_kernel(v1: wp.array(dtype=wp.vec3), v2: wp.array(dtype=wp.vec3), n: wp.array(dtype=wp.vec3),
                         d1: wp.array(dtype=wp.float32), d2: wp.array(dtype=wp.float32),
                         rho1: wp.array(dtype=wp.float32), rho2: wp.array(dtype=wp.float32),
                         targets: wp.array2d(dtype=wp.float32),
                         # outputs
                         v1_after: wp.array(dtype=wp.vec3), v2_after: wp.array(dtype=wp.vec3)):
    """Equal and opposite impulse from the predicted targets (momentum conserved exactly)."""
    i = wp.tid()
    m1 = sphere_mass(d1[i], rho1[i])
    m2 = sphere_mass(d2[i], rho2[i])
    J = contact_impulse(v1[i], v2[i], n[i], m1, m2, targets[i, 0], targets[i, 1])
    v1_after[i] = v1[i] - J / m1
    v2_after[i] = v2[i] + J / m2


@wp.kernel
def paper_features_kernel(v1: wp.array(dtype=wp.vec3), v2: wp.array(dtype=wp.vec3),
                          d1: wp.array(dtype=wp.float32), d2: wp.array(dtype=wp.float32),
                          rho1: wp.array(dtype=wp.float32), rho2: wp.array(dtype=wp.float32),
                          # outputs
                          features: wp.array2d(dtype=wp.float32)):
    """Paper-form features: row i the pair (1, 2), row N+i the swapped pair (2, 1)."""
    i = wp.tid()
    n_pairs = v1.shape[0]
    for k in range(3):
        features[i, k] = v1[i][k]
        features[i, 3 + k] = v2[i][k]
        features[n_pairs + i, k] = v2[i][k]
        features[n_pairs + i, 3 + k] = v1[i][k]
    features[i, 6] = d1[i]
    features[i, 7] = d2[i]
    features[i, 8] = rho1[i]
    features[i, 9] = rho2[i]
    features[n_pairs + i, 6] = d2[i]
    features[n_pairs + i, 7] = d1[i]
    features[n_pairs + i, 8] = rho2[i]
    features[n_pairs + i, 9] = rho1[i]


@wp.kernel
def paper_velocities_kernel(targets: wp.array2d(dtype=wp.float32),
                            # outputs
                            v1_after: wp.array(dtype=wp.vec3), v2_after: wp.array(dtype=wp.vec3)):
    """u, v, w of particle 1 (row i) and of particle 2 (swapped row N+i)."""
    i = wp.tid()
    n_pairs = v1_after.shape[0]
    v1_after[i] = wp.vec3(targets[i, 0], targets[i, 1], targets[i, 2])
    v2_after[i] = wp.vec3(targets[n_pairs + i, 0], targets[n_pairs + i, 1], targets[n_pairs + i, 2])


# ------------------------------------------------------------------------------ launch wrappers


def eval_forest(forest: Forest, features, out, *, rows_per_thread: int = 1, device=None, row_count=None,
                record: bool = False, thread_per_row: bool | None = None):
    """``out[row, t]`` = prediction of target t for ``features[row]`` (raw float32 features).

    ``rows_per_thread`` applies to the explicit layout; the perfect layout uses BLOCK_ROWS and takes an
    optional device ``row_count`` (int32 array: only the first row_count[0] rows). ``record``: launch nothing and
    return the recorded ``wp.Launch`` (``.launch()`` replays it without packing the arguments again; None for
    zero rows). ``thread_per_row`` (perfect layout; None: on a CUDA device): one thread per (row, target)
    (``eval_forest_perfect_rows_kernel``, the same bits) instead of BLOCK_ROWS rows per thread.
    """
    n_rows = features.shape[0]
    if n_rows == 0:
        return None
    device = wp.get_device(device or features.device)
    if forest.perfect:
        if not features.is_contiguous:
            raise ValueError("eval_forest: the perfect layout needs contiguous (row-major) features")
        if device.is_cuda if thread_per_row is None else thread_per_row:
            n_targets = forest.tree_start.shape[0] - 1
            return wp.launch(eval_forest_perfect_rows_kernel, dim=n_rows * n_targets,
                             inputs=[forest, features.flatten(), n_rows, features.shape[1], row_count],
                             outputs=[out], device=device, record_cmd=record)
        return wp.launch(eval_forest_perfect_kernel, dim=(n_rows + BLOCK_ROWS - 1) // BLOCK_ROWS,
                         inputs=[forest, features.flatten(), n_rows, features.shape[1], row_count], outputs=[out],
                         device=device, record_cmd=record)
    if row_count is not None:
        raise ValueError("eval_forest: row_count needs the perfect layout")
    rows_per_thread = max(1, int(rows_per_thread))
    return wp.launch(eval_forest_explicit_kernel, dim=(n_rows + rows_per_thread - 1) // rows_per_thread,
                     inputs=[forest, features, n_rows, rows_per_thread], outputs=[out], device=device,
                     record_cmd=record)


def contact_features(v1, v2, n, d1, d2, rho1, rho2, features, *, device=None) -> None:
    if v1.shape[0]:
        wp.launch(contact_features_kernel, dim=v1.shape[0], inputs=[v1, v2, n, d1, d2, rho1, rho2],
                  outputs=[features], device=device or v1.device)


def apply_contact(v1, v2, n, d1, d2, rho1, rho2, targets, v1_after, v2_after, *, device=None) -> None:
    if v1.shape[0]:
        wp.launch(apply_contact_kernel, dim=v1.shape[0], inputs=[v1, v2, n, d1, d2, rho1, rho2, targets],
                  outputs=[v1_after, v2_after], device=device or v1.device)


def paper_features(v1, v2, d1, d2, rho1, rho2, features, *, device=None) -> None:
    if v1.shape[0]:
        wp.launch(paper_features_kernel, dim=v1.shape[0], inputs=[v1, v2, d1, d2, rho1, rho2],
                  outputs=[features], device=device or v1.device)


def paper_velocities(targets, v1_after, v2_after, *, device=None) -> None:
    if v1_after.shape[0]:
        wp.launch(paper_velocities_kernel, dim=v1_after.shape[0], inputs=[targets],
                  outputs=[v1_after, v2_after], device=device or targets.device)


def contact_features_in_domain(v1, v2, n, d1, d2, rho1, rho2, domain, features, clamped, *, device=None) -> None:
    """Features clamped into ``domain`` (``ContactDomain``); ``clamped[0]`` counts the clamped pairs."""
    if v1.shape[0]:
        wp.launch(contact_features_in_domain_kernel, dim=v1.shape[0], inputs=[v1, v2, n, d1, d2, rho1, rho2, domain],
                  outputs=[features, clamped], device=device or v1.device)


def apply_admissible_contact(v1, v2, n, d1, d2, rho1, rho2, targets, friction_bound, v1_after, v2_after,
                             guard_counts, *, separation_slack: float = 0.0, device=None) -> None:
    """Guarded impulses; ``guard_counts`` (4,) int32 += [separation, Coulomb, energy, any] corrections."""
    if v1.shape[0]:
        wp.launch(apply_admissible_contact_kernel, dim=v1.shape[0],
                  inputs=[v1, v2, n, d1, d2, rho1, rho2, targets, float(friction_bound), float(separation_slack)],
                  outputs=[v1_after, v2_after, guard_counts], device=device or v1.device)


def admissible_targets(cos_angle, targets, friction_bound, guarded, flags, *, separation_slack: float = 0.0,
                       device=None) -> None:
    """Row-wise ``admissible_impulse``: ``guarded`` (N, 2) corrected targets, ``flags`` (N,) int32."""
    if cos_angle.shape[0]:
        wp.launch(admissible_targets_kernel, dim=cos_angle.shape[0], inputs=[cos_angle, targets, float(friction_bound),
                                                                     float(separation_slack)],
                  outputs=[guarded, flags], device=device or cos_angle.device)
