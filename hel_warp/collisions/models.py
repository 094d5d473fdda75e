"""Collision strategies ``surrogate`` (HELSCM, reference paper sec. 4.3) and ``dem`` (CFD-DEM reference).

Both follow the strategy interface of ``hel_warp.hel``: ``name``, ``accelerate(solver)`` (step 4 of
docs/developer/architecture.md "The step", before the push), ``counts()`` (per-step collision counts, a dict), and
for ``dem`` also ``advance(solver)``, which replaces the push.

- :class:`SurrogateCollision` (``mode="pairwise"`` default, ``mode="paper"``): end-of-step detection of
  overlapping parcels on a hash grid, post-collision velocities from the flattened XGBoost forest,
  applied as velocity jumps in ``accelerate`` (``kernels/collide.py`` has the equations and the
  no-double-counting argument).
- :class:`DemCollision` (``hel_warp/collisions/cfd_dem.py``, imported here for the name map): Hertz-Mindlin contacts
  sub-stepped at the DEM step of eq. (12) across the fluid step.

Names for the run side: ``hel_warp.hel.collision_model(name, ...)`` resolves ``surrogate``
(:class:`SurrogateCollision`), ``surrogate-paper`` (:class:`SurrogatePaperCollision`) and ``dem``
(:class:`DemCollision`) lazily from here; :data:`STRATEGIES` / :func:`make_collision` are the same map.
"""

from __future__ import annotations

import math

import numpy as np

from hel_warp.errors import ConfigError, HelWarpError
from hel_warp.collisions.cfd_dem import DemCollision
from hel_warp.collisions.pairs import DEFAULT_STREAMS, pair_counts


ORDERINGS = ("auto", "parallel", "sequential", "serial")
"""``SurrogateCollision(ordering=...)`` of the swept detection's events."""
DETECTIONS = ("swept", "overlap", "cell")
"""Pair detection of the ``pairwise`` surrogate: ``swept`` (continuous; the default for parcels of weight 1),
``overlap`` (the paper's test) or ``cell`` (stochastic per collision cell, ``hel_warp/collisions/cells.py``; the
default when a live parcel's weight exceeds 1)."""
GUARD_NAMES = ("separation", "coulomb", "energy", "domain_clamped", "late_overlap", "turned")
"""``counts()`` keys ``guard_<name>``: admissibility corrections and domain clamps (``kernels/collide.py``)."""
CELL_FACTOR = 2.0
"""Cells of the swept search's cell list (kernels/cell_list.py), in units of r_max + the mean reach (smaller cells
measured slower on the CPU: more rows per search)."""
MAX_SWEPT_CELLS = 4_000_000
"""Cells of the swept search's cell list at most (open space: the box of the live parcels' hash points): wider
cells beyond (a parcel far from the rest would otherwise size a huge box)."""
REACH_CUT_FACTOR = 4.0
"""R_cut of the swept searches, in units of the step's mean reach: the cell list is searched out to partners of
reach <= R_cut, the parcels above it are tested one by one (kernels/collide.py ``SweptArgs.reach_cut``; the
events do not depend on it). Measured on the colliding-streams rig (dt = 1e-3 s, where collisions raise the largest
reach from ~3 to ~8 mean reaches, and 1e-4 s): 2.5 lists ~20 % of the parcels after a few rounds, 6 hardly
narrows the searches; 4 was as fast as 2.5 or faster, within the noise of a shared machine."""
BOUND_CUT_FACTOR = 4.0
"""The event searches' cut on the path bounds (kernels/collide.py ``SweptArgs.bound_cut``), in units of the step's
mean reach, as R_cut (the events do not depend on it)."""
REACH_CUT_FLOOR = 0.5
"""R_cut is at least this fraction of r_max (overlap detection: reaches of zero, but end-of-contact turns grow some)."""
MAX_ROUNDS = 4096
"""Rounds of events per window of a step before the resolution stops and says so (``round_cap_hit``): an inelastic
collapse (infinitely many collisions in finite time, McNamara & Young 1994) would otherwise never end."""
WINDOW_REACH = 0.4
"""``windows="auto"``: a step that needs windows (``WINDOW_ROUNDS``) is resolved in windows of a mean reach (|v - u_f|
times half the window) of about this many particle radii (r_max). The step's paths and events do not depend on it;
the searches do: a search's ball has a radius of r_i + r_max + its path bound + the cut (4 mean reaches), so at
dt = 1e-3 s on the colliding-streams rig, where the mean reach is ~7 radii, one window searched ~2,000 parcels per
dirty parcel against tens in windows of 0.4 radii's reach (``scripts/profile_swept_rounds.py``)."""
WINDOW_ROUNDS = 30
"""``windows="auto"``: the step is cut into windows when the previous step needed at least this many rounds of
events beyond one per window (chains of collisions: the rounds' searches are then the cost); with fewer, each
window's full search costs more than it saves (a dilute cooling box at 1e-3 s: 9 rounds, 0.46 s in one window,
0.79 s in 13)."""
WINDOWS_SERIAL = 1.3
"""``windows="auto"`` with the serial queue: ceil(WINDOWS_SERIAL (mean reach / r_max) sqrt(events per parcel of the
last step)) windows. Measured fastest: a cooling box at 1e-3 s (0.18 events per parcel, reach 5 r) in 2-4, the rig
after its pile (0.44, 8.4 r) in 8, in the pile (7.8, 5.6 r) in 16."""
SERIAL_GROWTH = 4.0
"""``windows="auto"`` with the serial queue: the first window's forecast of the step's events per parcel is the last
step's times its growth over the step before, at most this factor (the colliding-streams rig's pile grows 3-4x per
step at dt = 1e-3 s while it forms); the later windows follow the events of the step so far."""
MAX_WINDOWS = 32
"""``windows="auto"``: at most this many windows per step (each window's first round searches every parcel)."""
WINDOWS_PER_ROOT_ROUND = 0.8
"""``windows="auto"``: at most this many windows per square root of the last step's rounds (each window's full
search of every parcel pays off over the rounds it makes cheaper; on the rig at 1e-3 s: ~100 rounds per step are
fastest in ~8 windows, ~2,500 in 16-32)."""


class SurrogateCollision:
    """``surrogate`` (HELSCM): detected pairs get post-collision velocities from the flattened forest.

    Modes:

    - ``pairwise`` (default; a ``contact``-form model), with the pair detection ``detection``:

      - ``swept`` (default): over the step every parcel flies on a straight line with its velocity at the
        step's start; a pair collides when its centres come within r_i + r_j while approaching, with the
        contact normal of the moment of touch, and after the impulse each parcel flies with its new velocity
        for the rest of the step. Several collisions of one parcel within the step are resolved in time
        order (rounds of mutually earliest events, ``kernels/collide.py``). The collision frequency and the
        impact geometry are then those of kinetic theory at any dt (docs/physics/references.md, "Collisions in a granular
        gas"). The in-step position changes are added after the push (:meth:`after_push`, or
        :meth:`correct_positions` when the caller moves the parcels itself), so nothing is left overlapping
        and nothing passes through.
      - ``overlap``: the paper's end-of-step test ``|x_i - x_j| < r_i + r_j`` on the positions at the step's
        start, normal along the centre line, approaching pairs only (the same machinery with paths of zero
        length: several partners in rounds, a separating pair is never collided again - the fix of the
        paper's sec. 8). Its collision count depends on dt; kept for comparison.

      - ``cell``: Bird's no-time-counter collisions per collision cell from the real number density (weights),
        impact geometry sampled (b^2 uniform, random azimuth), for parcels of many particles
        (``hel_warp/collisions/cells.py``, ``kernels/cell_collide.py``; options ``cell=CellConfig(...)``, random
        state ``seed`` and the steps taken, in :meth:`state`). ``detection=None`` (default) takes ``cell`` at a
        step where a live parcel's weight exceeds 1, else ``swept``.

      Each collision gets the equal and opposite impulse of the contact form, so momentum is conserved to
      float32 round-off.
    - ``paper`` (a ``paper``-form model): sec. 4.3 as written: per parcel the overlapping partners'
      velocities are averaged, and the model maps (own velocity, averaged partner velocity, sizes,
      densities) to the new velocity; every overlapping pair is used, approaching or not, and momentum is
      not guaranteed (the paper's scheme, kept for comparison).

    Parcels of weight w > 1 (pairwise mode): parcel i of w_i real particles and parcel j of w_j meet in
    ``min(w_i, w_j)`` real binary collisions (each real particle of the parcel with fewer particles hits
    one of the other's), each with the impulse J of one representative pair. Parcel i gets
    ``-min(w_i, w_j) J`` and parcel j ``+min(w_i, w_j) J``, i.e. ``dv_i = -(min/w_i) J/m_i``,
    ``dv_j = +(min/w_j) J/m_j``: equal weights give the binary outcome, the parcel momentum
    ``w_i m_i v_i + w_j m_j v_j`` is conserved. (Per real particle this collides w times too rarely for
    w > 1: the cell-based scheme of docs/developer/architecture.md is the fix.) Paper mode averages partner velocities
    with the partner weights as weights.

    ``periodic_box=(Lx, Ly, Lz)``: a triply periodic box [0, L) (collisions across the faces, minimum image);
    positions must lie in the box.

    ``counts()`` returns the counts of the last call, ``{name: int}``: ``collisions`` (real binary collisions
    resolved: sum of min(w_i, w_j); paper: the overlapping pairs that fed the model), ``surrogate_calls`` (pairs
    resolved), ``detected_pairs`` (pairs overlapping at the step's start, i.e. at the end of the previous step),
    ``separating_skipped`` (of those, the ones already separating), ``rounds`` (rounds that resolved
    collisions; paper: 0), ``windows`` (swept: the windows the step was resolved in, ``windows``), ``round_cap_hit`` (1 when ``max_rounds`` stopped the resolution), ``guard_separation``, ``guard_coulomb``,
    ``guard_energy`` (outcomes the admissibility guard corrected: kernels/forest.py ``admissible_impulse``),
    ``guard_domain_clamped`` (pairs whose features were clamped into the model's training domain),
    ``guard_late_overlap`` (swept: events whose pair was already overlapping at its time t > 0 - met unseen, e.g.
    out of order, or overlapping since the previous step's push), ``guard_turned`` (grazing outcomes still closing
    along the first-touch normal, turned to their end-of-contact normal), and per stream
    pair a <= b ``collisions_<a>_<b>``, ``surrogate_calls_<a>_<b>``, ``detected_pairs_<a>_<b>``.
    """

    def __init__(self, *, model_dir: str, mode: str = "pairwise", detection: str | None = None,
                 periodic_box=None, n_streams: int = DEFAULT_STREAMS, batched: bool = True,
                 max_rounds: int = MAX_ROUNDS, ordering: str = "auto", cell=None, seed: int = 0,
                 wall_events: bool = True, kick_first: bool = True, collision_events: bool = False,
                 particle_spin: bool = False, windows="auto"):
        from hel_warp.collisions.forest import load_forest

        if mode not in ("pairwise", "paper"):
            raise ConfigError(f"surrogate mode must be 'pairwise' or 'paper' (got {mode!r})")
        if detection is not None and detection not in DETECTIONS:
            raise ConfigError(f"detection must be one of {', '.join(DETECTIONS)} (got {detection!r})")
        if int(n_streams) != n_streams or n_streams < 1:
            raise ConfigError(f"n_streams must be a positive integer (got {n_streams!r})")
        if int(max_rounds) != max_rounds or max_rounds < 1:
            raise ConfigError(f"max_rounds must be a positive integer (got {max_rounds!r})")
        if ordering not in ORDERINGS:
            raise ConfigError(f"ordering must be one of {', '.join(ORDERINGS)} (got {ordering!r})")
        if windows != "auto" and not (isinstance(windows, (int, np.integer)) and not isinstance(windows, bool)
                                      and 1 <= windows <= 4096):
            raise ConfigError(f"windows must be 'auto' or an integer 1-4096 (got {windows!r})")
        self.windows = windows if windows == "auto" else int(windows)
        """Swept detection: the step is resolved in this many windows of equal length, one after the other, each
        with its own searches (``auto``: ``WINDOW_REACH`` for the parallel rounds; for the serial queue windows cut
        one at a time, ``WINDOWS_SERIAL`` and ``SERIAL_GROWTH``). The events and outcomes do not depend on it (the
        same paths, times and impulses); the cost does."""
        self._windows = 1
        self._rounds_last = 0
        """Rounds of events of the last swept step beyond one per window (``windows="auto"``; in :meth:`state`)."""
        self._rounds_prev = 0
        """``_rounds_last`` of the step before (the serial queue's forecast of a growing pile; in :meth:`state`)."""
        self.window_bounds = [0.0, 0.0]
        """Swept detection: the last step's window boundaries, s (from 0 to dt)."""
        self.window_events = []
        """Serial queue with ``windows="auto"``: the step's events before each window after the first (what chose its
        length)."""
        self.ordering = ordering
        """Swept detection: ``parallel``: rounds, every causally safe event of a round at once; ``sequential``: one
        event per round, the globally earliest (strict event-driven order, slow: the tests' reference); ``serial``:
        the strict order on one thread from an event queue (``kernels/collide.py`` ``swept_queue``: the same bits as
        ``sequential``, at a cost per event); ``auto`` (default): ``serial`` on the CPU (its kernels run on one
        thread anyway), ``parallel`` on CUDA and when the events are logged (``collision_events``)."""
        self.mode = mode
        self.auto_detection = detection is None and mode == "pairwise"
        """``detection=None``: ``cell`` at a step where a live parcel's weight exceeds 1, else ``swept``."""
        self.detection = (detection or "swept") if mode == "pairwise" else "overlap"
        self.name = "surrogate" if mode == "pairwise" else "surrogate-paper"
        self.periodic_box = _periodic_box(periodic_box)
        self.flat = load_forest(model_dir)
        want = "contact" if mode == "pairwise" else "paper"
        if self.flat.form != want and not (want == "contact" and self.flat.form == "contact_spin"):
            raise ConfigError(f"the {mode!r} surrogate mode needs a {want!r}-form model, {model_dir!r} holds a "
                              f"{self.flat.form!r}-form one; train with `hel-warp train --form {want}`")
        self.model_dir = model_dir
        self.n_streams = int(n_streams)
        self.max_rounds = int(max_rounds)
        self.batched = bool(batched)
        """Predict in batched forest evaluations (pairwise: each round's events; paper: the clustered
        particles): same results, faster; forests deeper than the perfect layout allows walk inline."""
        self._device = None
        self._counts = None
        self._grid = None
        self._grid_dims = None
        self._shift_pending = False
        from hel_warp.collisions.cells import CellCollisions

        self.cells = CellCollisions(config=cell, seed=seed, n_streams=self.n_streams)
        """The ``cell`` detection (its random state is :meth:`state`)."""
        self._solver_grid = None
        self._solver_fluid = None
        self._solver_local = None  # (CellGrid, parcel_eps_s) of the step, for CellConfig.local_density
        self.wall_events = bool(wall_events)
        """Swept detection in a solver with walls: True (default) reflects a parcel whose path crosses the wall
        within the step at the crossing, in time order with its collisions (it then collides on its reflected
        path); False leaves walls to the push's end-of-step reflection (the collisions of a parcel that bounces
        within a step are then found on its straight path through the wall, or one step late). Measured on the rig
        at dt = 1e-3 s (``hel-warp report``'s ``collision_rate_vs_dem``): the collision rate -55 % of the CFD-DEM's
        onsets without, +14 % with wall events; at 1e-4 s +3.3 % / +1.2 %; the run costs 1.1x."""
        self._walls = None
        self.kick_first = bool(kick_first)
        """Swept detection in a ``HelSolver``: True (default) applies the push's drag and gravity to the velocities
        before the collisions (``accelerate``), so that the swept paths are the paths the parcels take in the step
        (x + v_push t, the push's backward-Euler drift) and the step ends at the swept paths' ends (``advance``);
        False collides first and pushes the collided velocities (the paths of the detection then differ from the
        parcels' by (v - v_push) t: where dt / tau ~ 1, the rig's dense cloud at 1e-3 s, by about half the
        relative motion of neighbours)."""
        self._kicked = False
        self._x_scratch = None
        self.particle_spin = bool(particle_spin)
        """Pairwise mode, swept and cell detection: the collisions act at the contact point
        (docs/physics/spin-and-mixtures.md): the model is asked at the contact points' relative velocity (translation
        and spin, ``Particles.omega``) and its impulse turns the spins. Off: spinless collisions (the training
        data's). A ``HelSolver`` whose ``HelConfig.particle_spin`` is set switches it on."""
        self.record_events = bool(collision_events)
        """Keep every collision the swept (or overlap) detection resolves in a step, for :meth:`collision_events`
        (one logging launch per round; off by default)."""
        self._event_log = None
        self._events = None

    def collision_events(self) -> dict:
        """The collisions resolved by the last call (``collision_events=True``; swept and overlap detection), one
        entry each, in the layout of the ``dem`` strategy's ``onset_events``, sorted by (time, particle_a,
        particle_b): host arrays ``particle_a`` < ``particle_b`` (particle ids), ``speed`` (normal approach speed
        just before the impulse, m/s), ``time`` (s from the step's start), ``stream_a`` <= ``stream_b``;
        ``truncated`` is True when the step resolved more than the log held (it grows for the next step). Empty for
        a step of the cell detection or with the log off."""
        if self._events is None:
            return {"particle_a": np.zeros(0, np.int32), "particle_b": np.zeros(0, np.int32),
                    "speed": np.zeros(0, np.float32), "time": np.zeros(0), "stream_a": np.zeros(0, np.int32),
                    "stream_b": np.zeros(0, np.int32), "truncated": False}
        return dict(self._events)

    def _log_events_start(self, particles):
        """The event log's arrays for this step (None when off), its counter zeroed; sized from the last step's
        count (at least 2 per parcel)."""
        if not self.record_events:
            return None
        import warp as wp

        want = max(1024, 2 * particles.count)
        if self._event_log is not None:
            want = max(want, int(self._event_log[0].numpy()[0]))
        if self._event_log is None or self._event_log[1].shape[0] < want:
            dev = particles.v.device
            self._event_log = (wp.zeros(1, dtype=wp.int32, device=dev), wp.zeros((want, 4), dtype=wp.int32, device=dev),
                               wp.zeros((want, 2), dtype=wp.float32, device=dev))
        self._event_log[0].zero_()
        return self._event_log

    def _log_events_end(self, particles) -> None:
        """Host copy of the step's log, slots turned into particle ids (:meth:`collision_events`)."""
        count, log_int, log_float = self._event_log
        total = int(count.numpy()[0])
        m = min(total, log_int.shape[0])
        ij = log_int.numpy()[:m].copy()
        f = log_float.numpy()[:m].copy()
        ids = particles.particle_id.numpy()
        a, b = ids[ij[:, 0]], ids[ij[:, 1]]
        sa, sb = ij[:, 2], ij[:, 3]
        swap = a > b
        a, b = np.where(swap, b, a), np.where(swap, a, b)
        sa, sb = np.minimum(sa, sb), np.maximum(sa, sb)
        order = np.lexsort((b, a, f[:, 1]))
        self._events = {"particle_a": a[order].astype(np.int32), "particle_b": b[order].astype(np.int32),
                        "speed": f[order, 0], "time": f[order, 1].astype(np.float64),
                        "stream_a": sa[order].astype(np.int32), "stream_b": sb[order].astype(np.int32),
                        "truncated": total > m}

    def set_walls(self, shapes, params) -> None:
        """The wall geometry (``kernels.sdf.SdfShapes``) and restitution (``kernels.reflect.WallParams``) of the
        swept detection's wall events; ``shapes=None``: no walls. :meth:`accelerate` takes the solver's."""
        self._walls = None if shapes is None else (shapes, params)

    # ------------------------------------------------------------------ state on the device
    def _setup(self, particles) -> None:
        import warp as wp

        if self._device is not None and self._device == particles.device and self._capacity == particles.count:
            return
        dev = particles.device
        n = particles.count
        self._device = dev
        self._capacity = n
        from hel_warp.collisions.forest import PERFECT_MAX_DEPTH

        # each round's events predicted in one batch (perfect layout), else inline walks (explicit)
        self.batch_forest = None
        if self.batched and self.flat.max_depth <= PERFECT_MAX_DEPTH:
            self.batch_forest = self.flat.to_device(dev, layout="perfect")
        self.forest = self.flat.to_device(dev)
        s2 = self.n_streams * self.n_streams
        zeros = lambda shape, dtype: wp.zeros(shape, dtype=dtype, device=dev)  # noqa: E731
        self.detected = zeros(s2, wp.int32)
        self.calls = zeros(s2, wp.int32)
        self.collisions = zeros(s2, wp.int32)
        self.skipped = zeros(1, wp.int32)
        self.events_found = zeros(1, wp.int32)
        self.round_cap_hit = zeros(1, wp.int32)
        self.event_rounds = zeros(1, wp.int32)
        self.v_out = zeros(n, wp.vec3)
        self.v_swept = zeros(n, wp.vec3)
        """Velocities at the end of the last swept collide (the paths' last segments), for :meth:`correct_positions`."""
        self.paper_features = zeros((n, 10), wp.float32)
        self.paper_batch_row = zeros(n, wp.int32)
        self.paper_batch_out = zeros((n, 3), wp.float32)
        self.batch_count = zeros(1, wp.int32)
        self.reach_sum = zeros(1, wp.float32)
        from kernels.collide import SweptArgs

        a = SweptArgs()
        from kernels.cell_list import CellList

        a.cells = CellList()
        a.cells.slot_key, a.cells.slot_point = zeros(2 * n, wp.int32), zeros(2 * n, wp.int32)
        a.cells.slot_position = zeros(n, wp.vec3)
        self._cell_capacity = 0
        a.hash_point, a.base, a.shift = zeros(n, wp.vec3), zeros(n, wp.vec3), zeros(n, wp.vec3)
        a.anchor = a.hash_point
        self._anchor = zeros(n, wp.vec3)
        """The windows' anchors (kernels/collide.py ``SweptArgs.anchor``) when a step is resolved in several."""
        a.t_last, a.reach, a.reach_max = zeros(n, wp.float32), zeros(n, wp.float32), zeros(1, wp.float32)
        a.path_bound, a.wall_cache = zeros(n, wp.float32), zeros(n, wp.float32)
        a.large_index, a.large_count = zeros(n, wp.int32), zeros(1, wp.int32)
        a.bound_index, a.bound_count = zeros(n, wp.int32), zeros(1, wp.int32)
        a.listed = zeros(n, wp.int32)
        a.large_point = zeros(n, wp.vec3)
        a.event_key = wp.full(n, 0, dtype=wp.int64, device=dev)
        a.second_key = wp.full(n, 0, dtype=wp.int64, device=dev)
        a.second_ok = zeros(n, wp.int32)
        a.dirty, a.stamp, a.round = zeros(n, wp.int32), zeros(n, wp.int32), zeros(1, wp.int32)
        a.last_partner = zeros(n, wp.int32)
        a.event_i, a.event_j = zeros(n, wp.int32), zeros(n, wp.int32)
        a.event_time, a.event_normal = zeros(n, wp.float32), zeros(n, wp.vec3)
        a.features = zeros((n, len(self.flat.features)), wp.float32)
        a.batch_out = zeros((n, len(self.flat.targets)), wp.float32)
        a.spin_form = 1 if self.flat.form == "contact_spin" else 0
        a.batch_count = self.batch_count
        a.max_rounds = self.max_rounds
        a.guard = zeros(len(GUARD_NAMES), wp.int32)
        a.sequential = 1 if self.ordering == "sequential" else 0
        self._queue = (wp.zeros(4 * n + 64, dtype=wp.int64, device=dev), zeros(4 * n + 64, wp.int32),
                       zeros(1, wp.int32))
        """The serial resolution's event queue: heap keys, owners and size (``ordering`` serial)."""
        a.global_key = wp.full(1, 0, dtype=wp.int64, device=dev)
        a.blocker, a.blocked_round = zeros(n, wp.int32), zeros(n, wp.int32)
        a.blocker_key = wp.full(n, 0, dtype=wp.int64, device=dev)
        a.blocked_key = wp.full(n, 0, dtype=wp.int64, device=dev)
        if self.flat.form in ("contact", "contact_spin"):
            a.domain = self.flat.domain_to_device(dev)
        from kernels.reflect import make_wall_params
        from kernels.sdf import SdfShapes

        a.particle_omega = zeros(1, wp.vec3)  # set per call (collide) when particle_spin
        a.spin = 0
        a.walls = 0
        a.shapes = SdfShapes()  # no walls: an empty union (replaced by set_walls' geometry)
        a.shapes.center = zeros(1, wp.vec3)
        a.shapes.rotation = zeros(1, wp.mat33)
        a.shapes.half_extent = zeros(1, wp.vec3)
        a.shapes.kind = zeros(1, wp.int32)
        a.shapes.count = 0
        a.wall = make_wall_params()
        a.wall_count, a.wall_hits = zeros(1, wp.int32), zeros(1, wp.int32)
        a.wall_i, a.wall_time = zeros(n, wp.int32), zeros(n, wp.float32)
        self._empty_shapes = a.shapes
        self.swept = a
        self._swept_store = wp.empty(1, dtype=SweptArgs, device=dev)
        """The step's ``SweptArgs`` on the device for the round kernels (``kernels.collide.resolve_swept``)."""

    def _periodic_cells(self, cell: float):
        """Cells per axis and their common width that tile the periodic box exactly, near ``cell`` (at most a third
        of the smallest side: a search spans several cells rather than the box being one cell wide)."""
        box = self.periodic_box
        cell = min(cell, min(box) / 3.0)
        dims = tuple(int(np.floor(side / cell * (1.0 + 1e-6))) for side in box)
        width = box[0] / dims[0]
        if any(abs(side / d - width) > 1e-6 * width for side, d in zip(box, dims)):
            # a common cell width: the sides in the proportion of the dims
            width = max(side / d for side, d in zip(box, dims))
            dims = tuple(int(round(side / width)) for side in box)
            for first in range(int(np.floor(box[0] / cell * (1.0 + 1e-6))), 0, -1):
                if not any(abs(side / d - width) > 1e-6 * width for side, d in zip(box, dims)):
                    break  # else: the widest cells of at least ``cell`` that tile every side (e.g. 0.8 x 10 mm)
                width = box[0] / first
                dims = tuple(max(1, int(round(side / width))) for side in box)
            if any(abs(side / d - width) > 1e-6 * width for side, d in zip(box, dims)):
                raise ConfigError(f"periodic box sides {box} have no common cell width near {cell:.3g} m; use "
                                  "a cubic box or sides in small integer ratios")
        return dims, width

    def _cell_list(self, points, alive: np.ndarray, cell: float):
        """Sort the live ``points`` into the swept search's cell list (kernels/cell_list.py) of cells of at least
        ``cell``: in a periodic box cells that tile it exactly (a search wraps around the faces), in open space the
        box of the live points."""
        import warp as wp

        from kernels.cell_list import build_cell_list

        cells = self.swept.cells
        if self.periodic_box is not None:
            dims, width = self._periodic_cells(cell)
            origin = (0.0, 0.0, 0.0)
        else:
            p = points.numpy()[alive]
            lo, hi = p.min(axis=0), p.max(axis=0)
            width = float(cell)
            while True:
                dims = tuple(int(np.floor((h - l) / width)) + 1 for l, h in zip(lo, hi))
                if np.prod(dims, dtype=np.float64) <= MAX_SWEPT_CELLS:
                    break
                width *= 1.25
            origin = tuple(float(c) for c in lo)
        count = int(np.prod(dims))
        if count + 1 > self._cell_capacity:
            self._cell_capacity = int(1.5 * (count + 1))
            self._cell_start = wp.zeros(self._cell_capacity, dtype=wp.int32, device=self._device)
            self._cell_count = wp.zeros(self._cell_capacity, dtype=wp.int32, device=self._device)
        cells.origin, cells.inv_width, cells.dims = origin, 1.0 / float(width), dims
        cells.periodic = 0 if self.periodic_box is None else 1
        cells.cell_start = self._cell_start[: count + 1]
        build_cell_list(cells, points, self.swept.particle_alive, self._cell_count[: count + 1])

    def _hash_grid(self, points, cell: float, dims: int = 128):
        """A hash grid of ``points`` with cells of at least ``cell`` (kept between steps); in a periodic box the grid tiles the box exactly (dims x cell width = box side), so a query that
        crosses a face finds the images. ``dims``: hash cells per axis in open space (a build clears dims^3 cells:
        smaller is cheaper to build, larger aliases less)."""
        import warp as wp

        if self.periodic_box is None:
            dims = (int(dims),) * 3
            width = float(cell)
        else:
            dims, width = self._periodic_cells(cell)
        if self._grid_dims != dims:
            self._grid = wp.HashGrid(*dims, device=self._device)
            self._grid_dims = dims
        self._grid.reserve(points.shape[0])
        self._grid.build(points, float(width))
        return self._grid

    # ------------------------------------------------------------------ the strategy interface
    def accelerate(self, solver) -> None:
        """Velocity jumps of the step's collisions (``solver.pool.particles.v``); a_coll = 0 (the cell detection:
        its packing stress, ``CellConfig.packing_stress``)."""
        solver.fields.parcel_a_coll.zero_()
        self._solver_grid = solver.grid  # the cell detection's collision cells
        self._solver_fluid = getattr(solver, "cell_fluid", None)  # their fluid volumes
        fields = solver.fields
        self._solver_local = None
        if self.cells.config.local_density and getattr(fields, "parcel_eps_s", None) is not None:
            from hel_warp.parcels.coupling import parcel_grid

            self._solver_local = (parcel_grid(solver.grid, fields, self._solver_fluid), fields.parcel_eps_s)
        if getattr(getattr(solver, "config", None), "particle_spin", False):
            self.particle_spin = True
        walls = getattr(getattr(solver, "config", None), "walls", False)
        if self._walls is None and walls and getattr(solver, "shapes", None) is not None:
            self.set_walls(solver.shapes, solver.wall_params)
        particles = solver.pool.particles
        self._kicked = False
        # read_back 'output': the solver's host bounds of the live weights, radii and count choose the detection and
        # the cell lattice, and the cells plan their sub-steps on the device (no read)
        bounds = solver.live_bounds() if getattr(solver, "read_back", "step") == "output" else None
        # else one read for the choice of detection and the collisions (unless the kick below changes the velocities)
        extremes = (particles.live_extremes() if bounds is None and self.mode == "pairwise" and self.auto_detection
                    else None)
        uses_swept = self._uses_swept(particles, bounds[0] if bounds is not None else
                                      None if extremes is None else extremes[1])
        if not uses_swept and self.mode == "pairwise" and getattr(solver.config, "packing_stress", None) is None:
            self._packing_stress(solver)  # a solver's own packing stress (HelConfig.packing_stress) replaces it
        if self.kick_first and uses_swept:
            import warp as wp

            # the push's velocities now (drag, gravity; the drag impulses recorded for the gas), the positions
            # untouched (written to a scratch array): the collisions then act on the paths of the step
            if self._x_scratch is None or self._x_scratch.shape[0] != particles.x.shape[0]:
                self._x_scratch = wp.empty_like(particles.x)
            solver.fluid_push(particle_x_out=self._x_scratch)
            self._kicked = True
        self.collide(particles, solver.config.dt, extremes=None if self._kicked else extremes,
                     bounds=None if uses_swept else bounds)

    def _packing_stress(self, solver) -> None:
        """The cell detection's MP-PIC packing stress into ``solver.fields.parcel_a_coll`` (``CellConfig.
        packing_stress``; the deposited ``cell_eps_s`` of this step)."""
        cfg = self.cells.config if self.cells is not None else None
        fields = solver.fields
        if cfg is None or not cfg.packing_stress or getattr(fields, "cell_eps_s", None) is None:
            return
        from kernels.ktgf import cell_gradient, collision_acceleration, packing_pressure

        grid = solver.grid
        packing_pressure(fields.cell_eps_s, fields.cell_p_s, p_solid=cfg.packing_pressure, beta=cfg.packing_beta,
                         packed=cfg.packing_fraction, eps=1.0e-7)
        cell_gradient(grid.spacing, fields.cell_p_s, fields.cell_grad_p_s, periodic=grid.periodic)
        particles = solver.pool.particles
        collision_acceleration(grid.cell_grid(), 1.0e-6, particles.x, particles.density, fields.cell_grad_p_s,
                               fields.cell_eps_s, fields.parcel_a_coll, dt=solver.config.dt)

    def _uses_swept(self, particles, w_max: float | None = None) -> bool:
        """Whether :meth:`collide` takes the swept detection for these particles (``cell`` where auto-detection
        meets a parcel of weight > 1); ``w_max``: the largest live weight when the caller has it."""
        if self.mode != "pairwise":
            return False
        if self.auto_detection:
            if w_max is None:
                w_max = particles.live_extremes()[1]
            return not w_max > 1.0
        return self.detection == "swept"

    def advance(self, solver) -> None:
        """``HelSolver.push``: after a kick (:meth:`accelerate`) the parcels drift along their swept paths (x += v dt
        + the in-step changes); otherwise the solver's push."""
        if not self._kicked:
            solver.fluid_push()
            return
        from kernels.collide import launch_drift_swept

        particles = solver.pool.particles
        launch_drift_swept(self.swept.shift, particles.alive, particles.v, float(solver.config.dt), particles.x)
        self._shift_pending = False
        self._kicked = False

    def after_push(self, solver) -> None:
        """Called by ``HelSolver.push`` after the parcels moved: the in-step position corrections (swept)."""
        self.correct_positions(solver.pool.particles)

    def collide(self, particles, dt: float | None = None, *, extremes: tuple | None = None,
                bounds: tuple | None = None) -> None:
        """Resolve the collisions of ``particles`` in the coming step of ``dt`` (swept; required) or at the current
        positions (overlap, paper), updating the velocities in place. With swept detection the caller then moves
        the parcels with their new velocities and calls :meth:`correct_positions`. ``extremes``:
        ``particles.live_extremes()`` when the caller has them for the current velocities. ``bounds``: (max weight,
        max radius, live count) host upper bounds (``HelSolver.live_bounds``): the cell detection then plans its
        sub-steps on the device (``CellCollisions.collide``'s ``device_extremes``) and, on a grid's or a periodic
        box's unshifted lattice, reads nothing back; the non-finite velocities its read would catch are the
        solver's output check's (``HelSolver.check_finite``). Between two outputs the bounds may exceed the live
        values where parcels leave (an outlet): the choice of detection, the lattice and the approach filter then
        follow the bounds, so an open flow's run departs from the per-step reading one's; a closed one's gives the
        same bits."""
        self._setup(particles)
        for arr in (self.detected, self.calls, self.collisions, self.skipped, self.round_cap_hit,
                    self.event_rounds, self.swept.round, self.swept.guard, self.swept.wall_hits):
            arr.zero_()
        self._counts = None
        self._events = None
        self._shift_pending = False
        if bounds is not None and self.mode == "pairwise" and (
                self.detection == "cell" if not self.auto_detection else bounds[0] > 1.0):
            if bounds[2] == 0:
                return
            self.detection = "cell"
            self._collide_cells(particles, dt, device_extremes=(particles.launch_live_extremes(), tuple(bounds)))
            return
        if extremes is None:
            extremes = particles.live_extremes()  # one read-back, not four arrays
        v_max, w_max, r_max, n_alive, bad = extremes
        if bad:
            raise HelWarpError(f"{bad} live parcels have a NaN or infinite velocity, weight or radius before the "
                               "collisions: the step blew up (reduce dt) or the input holds NaN")
        extremes = (v_max, w_max, r_max, n_alive)
        if n_alive == 0:
            return
        if self.mode == "paper":
            self._collide_paper(particles, r_max)
            return
        if self.auto_detection:
            self.detection = "cell" if w_max > 1.0 else "swept"
        if self.detection == "cell":
            self._collide_cells(particles, dt, extremes=extremes)
            return
        alive = particles.alive.numpy().astype(bool)
        if self.detection == "swept":
            if dt is None or not dt > 0 or not np.isfinite(dt):
                raise ConfigError(f"swept detection needs the step dt > 0 (got {dt!r})")
            sweep = float(dt)
        else:
            sweep = 0.0
        self._collide_pairwise(particles, r_max, sweep, alive)

    def _collide_cells(self, particles, dt, **extremes) -> None:
        """The cell detection's step (``CellCollisions.collide``) with this strategy's forests, spin, box or grid,
        fluid mask, walls and local solids fraction; ``extremes``: its ``extremes=`` or ``device_extremes=``."""
        periodic = self.periodic_box is not None
        self.cells.collide(particles, dt, self.forest, self.swept.domain, batch_forest=self.batch_forest,
                           particle_spin=self.particle_spin, spin_form=self.flat.form == "contact_spin",
                           periodic_box=self.periodic_box, grid=None if periodic else self._solver_grid,
                           fluid=self._solver_fluid, walls=self._walls,
                           local=None if periodic else self._solver_local, **extremes)

    def _collide_pairwise(self, particles, r_max: float, sweep: float, alive: np.ndarray) -> None:
        import warp as wp

        from kernels.collide import launch_swept_start, launch_swept_window, resolve_swept

        a = self.swept
        a.particle_x, a.particle_radius = particles.x, particles.radius
        a.particle_density, a.particle_weight = particles.density, particles.weight
        a.particle_alive, a.particle_stream = particles.alive, particles.stream
        a.n_streams, a.dt, a.max_radius = self.n_streams, sweep, r_max
        box = self.periodic_box
        a.periodic = 0 if box is None else 1
        a.box = (0.0, 0.0, 0.0) if box is None else box
        v = particles.v.numpy()[alive]
        a.frame_velocity = tuple(float(c) for c in v.astype(np.float64).mean(axis=0)) if sweep > 0 else (0.0,) * 3
        walls = self._walls if (self.wall_events and sweep > 0 and box is None) else None
        a.walls = 0 if walls is None else 1
        a.shapes = self._empty_shapes if walls is None else walls[0]
        if walls is not None:
            a.wall = walls[1]
        a.reach_max.zero_()
        self.reach_sum.zero_()
        launch_swept_start(a, particles.v, a.reach_max, self.reach_sum)
        reach_max = float(a.reach_max.numpy()[0])
        reach_mean = float(self.reach_sum.numpy()[0]) / max(1, int(np.count_nonzero(alive)))
        if box is not None and 2.0 * (r_max + reach_max) > 0.5 * min(box):
            raise ConfigError(f"the periodic box {box} is too small for the collision search of this step "
                              f"({2.0 * (r_max + reach_max):.3g} m must stay below half the box side): enlarge the "
                              "box (more particles) or shorten dt")
        log = self._log_events_start(particles)
        serial = self._serial(particles, log)
        n_alive = int(np.count_nonzero(alive))
        windows = self._window_count(reach_mean, r_max, serial, n_alive) if sweep > 0.0 else 1
        # the serial queue's events do not depend on the windows: with "auto" each window's length is chosen
        # after the one before, from the events per parcel this step has had so far (a pile that grows within the
        # step gets shorter windows at once); the parallel rounds keep equal windows (their bits depend on them)
        adaptive = serial and self.windows == "auto" and sweep > 0.0
        reach_step = reach_mean  # the step's mean reach (the windows' own replace reach_mean below)
        self._shift_pending = sweep > 0.0
        a.spin = 1 if self.particle_spin else 0
        if self.particle_spin:
            a.particle_omega = particles.omega
        a.t_start, a.t_end, a.first_round = 0.0, sweep, 0
        a.anchor = a.hash_point  # one window: the searches' point is the hash point
        bounds = [sweep * k / windows for k in range(windows)] + [sweep]
        self.window_events = []
        k = 0
        while k < len(bounds) - 1:
            if adaptive and k > 0:
                done = bounds[k] / sweep
                events = int(self.event_rounds.numpy()[0])
                self.window_events.append(events)
                # the events per parcel of the step so far, extrapolated; never below the forecast (a pile that
                # forms late in the step)
                per_parcel = max(events / max(1, n_alive) / done, self._serial_forecast(n_alive))
                left = max(1, round(self._serial_windows(reach_step, r_max, per_parcel) * (1.0 - done)))
                bounds = bounds[:k + 1] + [bounds[k] + (sweep - bounds[k]) * (m + 1) / left for m in range(left)]
                bounds[-1] = sweep
            if len(bounds) > 2:
                # the window [t_start, t_end]: anchors at its middle, reaches over it, every parcel searched again
                a.t_start = bounds[k]
                a.t_end = bounds[k + 1]
                a.first_round = 0 if k == 0 else int(a.round.numpy()[0])
                a.anchor = self._anchor
                a.reach_max.zero_()
                self.reach_sum.zero_()
                launch_swept_window(a, particles.v, a.reach_max, self.reach_sum)
                reach_mean = float(self.reach_sum.numpy()[0]) / max(1, int(np.count_nonzero(alive)))
            a.max_rounds = a.first_round + self.max_rounds
            # cells of a typical search; the rounds search the cells out to partners of reach <= R_cut (the few
            # above it are listed), so one collision that raises a reach far above the rest does not widen every
            # search
            self._cell_list(a.anchor, alive, CELL_FACTOR * (r_max + reach_mean))
            a.reach_cut = max(REACH_CUT_FACTOR * reach_mean if reach_mean > 0.0 else 0.0, REACH_CUT_FLOOR * r_max)
            a.bound_cut = max(BOUND_CUT_FACTOR * reach_mean if reach_mean > 0.0 else 0.0, REACH_CUT_FLOOR * r_max)
            resolve_swept(a, self.forest, particles.v, self.events_found, self.event_rounds, self.round_cap_hit,
                          self.calls, self.collisions, self.detected, self.skipped, batch_forest=self.batch_forest,
                          args_store=self._swept_store, particle_omega=particles.omega, event_log=log,
                          queue=self._queue if serial else None)
            k += 1
        windows = len(bounds) - 1
        self._windows = windows
        self.window_bounds = bounds
        if log is not None:
            self._log_events_end(particles)
        if sweep > 0.0:
            self._rounds_prev = self._rounds_last
            self._rounds_last = max(0, int(self.event_rounds.numpy()[0]) - windows)
            wp.copy(self.v_swept, particles.v)

    def _serial(self, particles, log) -> bool:
        """Whether this step's swept events are resolved from the serial queue (``ordering``)."""
        if self.ordering == "serial":
            return True
        if self.ordering != "auto" or log is not None:
            return False
        device = particles.v.device
        return device.is_cpu and not device.is_capturing

    def _window_count(self, reach_mean: float, r_max: float, serial: bool = False, alive: int = 1) -> int:
        """Windows of the step (``windows``): ``auto`` cuts a step after one of many rounds (``WINDOW_ROUNDS``) so
        that the mean reach of a window is about ``WINDOW_REACH`` particle radii (the searches' balls shrink with
        it), at most ``WINDOWS_PER_ROOT_ROUND`` sqrt(rounds) and ``MAX_WINDOWS``."""
        if self.windows != "auto":
            return int(self.windows)
        if not reach_mean > 0.0 or not r_max > 0.0:
            return 1
        if serial:
            # the serial queue: a window's full search costs ~N searches, an event a few; the last step's events
            # per parcel (its "rounds" are its events), grown as from the step before (a pile forming: up to
            # SERIAL_GROWTH times), set how far the balls should shrink
            return self._serial_windows(reach_mean, r_max, self._serial_forecast(alive))
        if self._rounds_last < WINDOW_ROUNDS:
            return 1
        by_rounds = math.ceil(WINDOWS_PER_ROOT_ROUND * math.sqrt(self._rounds_last))
        return int(min(MAX_WINDOWS, by_rounds, max(1, math.ceil(reach_mean / (WINDOW_REACH * r_max)))))

    def _serial_forecast(self, alive: int) -> float:
        """The serial queue's forecast of this step's events per live parcel: the last step's, grown as from the
        step before (at most ``SERIAL_GROWTH`` times)."""
        per_parcel = self._rounds_last / max(1, alive)
        if self._rounds_prev > 0:
            per_parcel *= min(SERIAL_GROWTH, max(1.0, self._rounds_last / self._rounds_prev))
        return per_parcel

    @staticmethod
    def _serial_windows(reach_mean: float, r_max: float, per_parcel: float) -> int:
        """The serial queue's windows per step for ``per_parcel`` events per live parcel and step (``WINDOWS_SERIAL``)."""
        return int(min(MAX_WINDOWS, max(1, math.ceil(WINDOWS_SERIAL * reach_mean / r_max * math.sqrt(per_parcel)))))

    def correct_positions(self, particles) -> None:
        """Add the in-step position corrections of the last swept or cell :meth:`collide` (once; a no-op otherwise)."""
        if self.detection == "cell":
            self.cells.correct_positions(particles)
            return
        if not self._shift_pending:
            return
        from kernels.collide import launch_add_swept_shift

        launch_add_swept_shift(self.swept.shift, self.swept.t_last, self.v_swept, particles.alive, particles.v,
                               particles.x)
        self._shift_pending = False

    def _collide_paper(self, particles, r_max: float) -> None:
        import warp as wp

        from kernels.collide import PaperArgs, launch_paper_update

        grid = self._hash_grid(particles.x, 2.0 * r_max)
        args = PaperArgs()
        args.grid = grid.id
        args.particle_x, args.particle_v = particles.x, particles.v
        args.particle_radius, args.particle_density = particles.radius, particles.density
        args.particle_weight, args.particle_alive = particles.weight, particles.alive
        args.particle_stream, args.max_radius, args.n_streams = particles.stream, float(r_max), self.n_streams
        box = self.periodic_box
        args.periodic = 0 if box is None else 1
        args.box = (0.0, 0.0, 0.0) if box is None else box
        args.batch_row, args.batch_count = self.paper_batch_row, self.batch_count
        launch_paper_update(args, self.forest, self.paper_features, self.v_out, self.calls,
                            batch_forest=self.batch_forest, batch_out=self.paper_batch_out)
        wp.copy(particles.v, self.v_out)
        wp.copy(self.detected, self.calls)
        wp.copy(self.collisions, self.calls)

    def state(self) -> dict:
        """Checkpoint entries: the cell detection's random state (seed, steps taken) and the swept detection's last
        rounds (``swept_rounds``: they choose the next step's windows, ``windows="auto"``)."""
        return {**self.cells.state(), "swept_rounds": np.array(self._rounds_last, np.int64),
                "swept_rounds_prev": np.array(self._rounds_prev, np.int64)}

    def set_state(self, state: dict) -> None:
        self.cells.set_state(state)
        if "swept_rounds" in state:
            self._rounds_last = int(np.asarray(state["swept_rounds"]))
        if "swept_rounds_prev" in state:
            self._rounds_prev = int(np.asarray(state["swept_rounds_prev"]))

    def count_arrays(self):
        """The device arrays :meth:`counts` reads and the host values it needs, taken now: ({name: wp.array},
        extras), for a caller that copies the arrays on the device every step and reads them at output intervals
        (``hel_warp.runs.run.Run``, ``HelConfig.read_back`` 'output'); None where nothing is on the device yet."""
        if self.detection == "cell" and self.mode == "pairwise":
            return self.cells.count_arrays()
        if self._device is None:
            return None
        arrays = {"detected": self.detected, "calls": self.calls, "collisions": self.collisions,
                  "skipped": self.skipped, "rounds": self.event_rounds, "cap": self.round_cap_hit,
                  "guard": self.swept.guard, "wall_events": self.swept.wall_hits}
        return arrays, {"windows": self._windows if self.detection == "swept" else 1}

    def counts_from(self, host: dict, extras: dict) -> dict:
        """:meth:`counts` from host copies of :meth:`count_arrays` (the same names) and its extras."""
        if "cell_counts" in host:
            return self.cells.counts_from(host, extras)
        s = self.n_streams
        detected, calls, collisions = (np.asarray(host[k]).reshape(s, s) for k in ("detected", "calls", "collisions"))
        return {"collisions": int(collisions.sum()), "surrogate_calls": int(calls.sum()),
                "detected_pairs": int(detected.sum()), "separating_skipped": int(host["skipped"][0]),
                "rounds": int(host["rounds"][0]), "round_cap_hit": int(host["cap"][0]),
                "wall_events": int(host["wall_events"][0]), "windows": extras["windows"],
                **{f"guard_{name}": int(k) for name, k in zip(GUARD_NAMES, host["guard"])},
                **pair_counts("collisions", collisions), **pair_counts("surrogate_calls", calls),
                **pair_counts("detected_pairs", detected)}

    def counts(self) -> dict:
        """Counts of the last :meth:`collide` (host read): totals and per stream pair (see the class)."""
        if self.detection == "cell" and self.mode == "pairwise":
            return self.cells.counts()
        if self._counts is None:
            staged = self.count_arrays()
            if staged is None:
                s = self.n_streams
                zero = np.zeros(s * s, np.int64)
                host = {"detected": zero, "calls": zero, "collisions": zero, "skipped": [0], "rounds": [0],
                        "cap": [0], "guard": np.zeros(len(GUARD_NAMES), np.int64), "wall_events": [0]}
                extras = {"windows": self._windows if self.detection == "swept" else 1}
            else:
                host, extras = {k: a.numpy() for k, a in staged[0].items()}, staged[1]
            self._counts = self.counts_from(host, extras)
        return dict(self._counts)


def _periodic_box(box):
    """Validated (Lx, Ly, Lz) floats, or None."""
    if box is None:
        return None
    try:
        sides = tuple(float(v) for v in box)
    except (TypeError, ValueError):
        raise ConfigError(f"periodic_box must be three box sides in m (got {box!r})") from None
    if len(sides) != 3 or not all(np.isfinite(v) and v > 0 for v in sides):
        raise ConfigError(f"periodic_box must be three positive finite sides in m (got {box!r})")
    return sides


class SurrogatePaperCollision(SurrogateCollision):
    """``surrogate-paper``: :class:`SurrogateCollision` in ``paper`` mode (a ``paper``-form model)."""

    def __init__(self, *, model_dir: str, n_streams: int = DEFAULT_STREAMS, periodic_box=None):
        super().__init__(model_dir=model_dir, mode="paper", n_streams=n_streams, periodic_box=periodic_box)


def make_collision(name: str, **kwargs):
    """The strategy of run name ``name``: ``surrogate`` / ``surrogate-paper`` (``model_dir=``) or ``dem``."""
    if name == "surrogate":
        return SurrogateCollision(mode="pairwise", **kwargs)
    if name == "surrogate-paper":
        return SurrogatePaperCollision(**kwargs)
    if name == "dem":
        return DemCollision(**kwargs)
    raise ConfigError(f"unknown collision model {name!r}; this module provides {', '.join(STRATEGIES)}")


STRATEGIES = {"surrogate": SurrogateCollision, "surrogate-paper": SurrogatePaperCollision, "dem": DemCollision}
"""Run names -> strategy classes (``hel_warp.hel.COLLISION_MODELS`` resolves the same names lazily)."""
