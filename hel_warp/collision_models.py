"""Collision strategies ``surrogate`` (HELSCM, reference paper sec. 4.3) and ``dem`` (CFD-DEM reference).

Both follow the strategy interface of ``hel_warp.hel``: ``name``, ``accelerate(solver)`` (step 4 of
ARCHITECTURE.md "The step", before the push), ``counts()`` (per-step collision counts, a dict), and
for ``dem`` also ``advance(solver)``, which replaces the push.

- :class:`SurrogateCollision` (``mode="pairwise"`` default, ``mode="paper"``): end-of-step detection of
  overlapping parcels on a hash grid, post-collision velocities from the flattened XGBoost forest,
  applied as velocity jumps in ``accelerate`` (``kernels/collide.py`` has the equations and the
  no-double-counting argument).
- :class:`DemCollision`: Hertz-Mindlin contacts (``kernels/contacts.py``, ``kernels/hertz.py``) sub-stepped
  with velocity Verlet (``kernels/integrate.py``) at the DEM step of eq. (12) across the fluid step.

Names for the run side: ``hel_warp.hel.collision_model(name, ...)`` resolves ``surrogate``
(:class:`SurrogateCollision`), ``surrogate-paper`` (:class:`SurrogatePaperCollision`) and ``dem``
(:class:`DemCollision`) lazily from here; :data:`STRATEGIES` / :func:`make_collision` are the same map.
"""

from __future__ import annotations

import math

import numpy as np

from hel_warp.errors import ConfigError, require_positive
from hel_warp.material import Material

DEFAULT_STREAMS = 4
"""Stream tags counted separately (tags outside [0, n_streams) count as the nearest end)."""


def _pair_counts(prefix: str, matrix: np.ndarray) -> dict:
    """{"<prefix>_<a>_<b>": count} for every stream pair a <= b of an (S, S) upper-triangular count matrix.

    Every pair is listed (zeros too), so the keys are the same at every step (one column each in the run
    output)."""
    s = matrix.shape[0]
    return {f"{prefix}_{a}_{b}": int(matrix[a, b]) for a in range(s) for b in range(a, s)}


class _PairDetector:
    """Hash grid + compact pair list (i < j, overlapping) on the parcels' device; grows as needed."""

    def __init__(self, device, capacity: int):
        import warp as wp

        self.device = device
        self.grid = wp.HashGrid(128, 128, 128, device=device)
        self.grid.reserve(capacity)
        self.pair_count = wp.zeros(capacity, dtype=wp.int32, device=device)
        self.pair_offset = wp.zeros(capacity, dtype=wp.int32, device=device)
        self.pair_capacity = 0
        self.n_pairs = 0
        self._grow_pairs(max(16, capacity))

    def _grow_pairs(self, needed: int) -> None:
        import warp as wp

        cap = max(needed, 2 * self.pair_capacity)
        self.pair_i = wp.zeros(cap, dtype=wp.int32, device=self.device)
        self.pair_j = wp.zeros(cap, dtype=wp.int32, device=self.device)
        self.pair_state = wp.zeros(cap, dtype=wp.int32, device=self.device)
        self.pair_capacity = cap

    def max_radius(self, particles) -> float:
        alive = particles.alive.numpy().astype(bool)
        return float(particles.radius.numpy()[alive].max()) if alive.any() else 0.0

    def build(self, particles, max_radius: float) -> None:
        """Hash grid of the current positions (cell 2 r_max)."""
        self.grid.build(particles.x, 2.0 * max_radius)

    def detect(self, particles, max_radius: float) -> int:
        from kernels.collide import detect_pairs, fill_pair_list

        self.build(particles, max_radius)
        detect_pairs(self.grid, particles, max_radius, self.pair_count, self.pair_offset)
        n = particles.count  # total pairs: the one host read of the detection (exclusive scan + last count)
        n_pairs = int(self.pair_offset[n - 1:n].numpy()[0] + self.pair_count[n - 1:n].numpy()[0])
        if n_pairs > self.pair_capacity:
            self._grow_pairs(n_pairs)
        if n_pairs:
            fill_pair_list(self.grid, particles, max_radius, self.pair_offset, self.pair_i, self.pair_j)
        self.n_pairs = n_pairs
        return n_pairs

    def pairs(self) -> np.ndarray:
        """(n_pairs, 2) host copy of the pair list (i < j, rows sorted)."""
        return np.stack([self.pair_i.numpy()[:self.n_pairs], self.pair_j.numpy()[:self.n_pairs]], axis=1)


class SurrogateCollision:
    """``surrogate`` (HELSCM): detected pairs get post-collision velocities from the flattened forest.

    Modes:

    - ``pairwise`` (default; a ``contact``-form model): only approaching pairs,
      ``(v_j - v_i).(x_j - x_i) < 0``, collide; each gets the equal and opposite impulse of the contact
      form (features in the contact frame, normal along the centre line). Several partners in one step
      are resolved in rounds of disjoint pairs (a deterministic greedy matching, sequential impulses in
      pair-index order), so no impulse is double counted and momentum is conserved to float32 round-off.
      A pair that overlaps but already separates (e.g. the pair collided at the previous step and still
      overlapping) is skipped: the repeated-detection fix.
    - ``paper`` (a ``paper``-form model): sec. 4.3 as written: per parcel the overlapping partners'
      velocities are averaged, and the model maps (own velocity, averaged partner velocity, sizes,
      densities) to the new velocity; every overlapping pair is used, approaching or not, and momentum is
      not guaranteed (the paper's scheme, kept for comparison).

    Parcels of weight w > 1 (pairwise mode): parcel i of w_i real particles and parcel j of w_j meet in
    ``min(w_i, w_j)`` real binary collisions (each real particle of the parcel with fewer particles hits
    one of the other's), each with the impulse J of one representative pair. Parcel i gets
    ``-min(w_i, w_j) J`` and parcel j ``+min(w_i, w_j) J``, i.e. ``dv_i = -(min/w_i) J/m_i``,
    ``dv_j = +(min/w_j) J/m_j``: equal weights give the binary outcome, the parcel momentum
    ``w_i m_i v_i + w_j m_j v_j`` is conserved, and the parcel with more particles changes its mean
    velocity only by the share of its particles that collided. Paper mode averages partner velocities
    with the partner weights as weights.

    Velocity jumps are applied in :meth:`accelerate` (before the push) to the positions at the end of
    the previous step ("end of step" detection, as in the paper). ``counts()`` returns the counts of the
    last call, ``{name: int}``: ``detected_pairs``, ``surrogate_calls`` (pairwise: approaching pairs
    resolved; paper: the pairs that fed the model), ``separating_skipped``, ``rounds`` (matching rounds),
    and per stream pair a <= b ``detected_pairs_<a>_<b>``, ``surrogate_calls_<a>_<b>``.
    """

    def __init__(self, *, model_dir: str, mode: str = "pairwise", n_streams: int = DEFAULT_STREAMS,
                 batched: bool = True):
        from hel_warp.forest import load_forest

        if mode not in ("pairwise", "paper"):
            raise ConfigError(f"surrogate mode must be 'pairwise' or 'paper' (got {mode!r})")
        if int(n_streams) != n_streams or n_streams < 1:
            raise ConfigError(f"n_streams must be a positive integer (got {n_streams!r})")
        self.mode = mode
        self.name = "surrogate" if mode == "pairwise" else "surrogate-paper"
        self.flat = load_forest(model_dir)
        want = "contact" if mode == "pairwise" else "paper"
        if self.flat.form != want:
            raise ConfigError(f"the {mode!r} surrogate mode needs a {want!r}-form model, {model_dir!r} holds a "
                              f"{self.flat.form!r}-form one; train with `hel-warp train --form {want}`")
        self.model_dir = model_dir
        self.n_streams = int(n_streams)
        self.batched = bool(batched)
        """Predict in batched forest evaluations (pairwise: each round's pairs; paper: the clustered
        particles): same results, faster; forests deeper than the perfect layout allows walk inline."""
        self._device = None
        self._counts = None

    # ------------------------------------------------------------------ state on the device
    def _setup(self, particles) -> None:
        import warp as wp

        if self._device is not None and self._device == particles.device and self._capacity == particles.count:
            return
        dev = particles.device
        n = particles.count
        self._device = dev
        self._capacity = n
        from hel_warp.forest import PERFECT_MAX_DEPTH

        # pairwise: each round's pairs predicted in one batch (perfect layout), else inline walks (explicit)
        self.batch_forest = None
        if self.batched and self.flat.max_depth <= PERFECT_MAX_DEPTH:
            self.batch_forest = self.flat.to_device(dev, layout="perfect")
        self.forest = self.flat.to_device(dev)
        self.detector = _PairDetector(dev, n)
        s2 = self.n_streams * self.n_streams
        self.detected = wp.zeros(s2, dtype=wp.int32, device=dev)
        self.calls = wp.zeros(s2, dtype=wp.int32, device=dev)
        self.skipped = wp.zeros(1, dtype=wp.int32, device=dev)
        self.rounds = wp.zeros(1, dtype=wp.int32, device=dev)
        self.more_rounds = wp.zeros(1, dtype=wp.int32, device=dev)
        self.owner = wp.zeros(n, dtype=wp.int32, device=dev)
        self.v_out = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.paper_features = wp.zeros((n, 10), dtype=wp.float32, device=dev)
        self.paper_batch_row = wp.zeros(n, dtype=wp.int32, device=dev)
        self.paper_batch_out = wp.zeros((n, 3), dtype=wp.float32, device=dev)
        self.pair_features = wp.zeros((16, 6), dtype=wp.float32, device=dev)
        self._grow_batch(16)
        self.batch_count = wp.zeros(1, dtype=wp.int32, device=dev)

    # ------------------------------------------------------------------ the strategy interface
    def accelerate(self, solver) -> None:
        """Velocity jumps of the detected collisions (``solver.pool.particles.v``); a_coll = 0."""
        solver.fields.parcel_a_coll.zero_()
        self.collide(solver.pool.particles)

    def collide(self, particles) -> None:
        """Detect overlapping parcels of ``particles`` and apply the surrogate's velocities in place."""
        self._setup(particles)
        for arr in (self.detected, self.calls, self.skipped, self.rounds):
            arr.zero_()
        self._counts = None
        det = self.detector
        r_max = det.max_radius(particles)
        if r_max <= 0.0:
            return
        if self.mode == "paper":
            self._collide_paper(particles, r_max)
        else:
            self._collide_pairwise(particles, r_max)

    def _collide_pairwise(self, particles, r_max: float) -> None:
        import warp as wp

        from kernels.collide import PairwiseArgs, launch_count_detected, resolve_pairwise

        det = self.detector
        n_pairs = det.detect(particles, r_max)
        if not n_pairs:
            return
        if self.pair_features.shape[0] < det.pair_capacity:
            self.pair_features = wp.zeros((det.pair_capacity, 6), dtype=wp.float32, device=self._device)
            self._grow_batch(det.pair_capacity)
        launch_count_detected(n_pairs, det.pair_i, det.pair_j, particles.stream, self.n_streams, self.detected,
                              det.pair_state)
        args = PairwiseArgs()
        args.pair_i, args.pair_j, args.owner = det.pair_i, det.pair_j, self.owner
        args.particle_x, args.particle_radius = particles.x, particles.radius
        args.particle_density, args.particle_weight = particles.density, particles.weight
        args.particle_stream, args.n_streams = particles.stream, self.n_streams
        args.batch_row, args.batch_count = self.batch_row, self.batch_count
        # batched rounds write their rows into the same feature array the inline walks use (never both)
        args.batch_features, args.batch_out = self.pair_features, self.batch_out
        resolve_pairwise(n_pairs, args, self.forest, det.pair_state, self.pair_features, particles.v, self.calls,
                         self.skipped, self.more_rounds, self.rounds, batch_forest=self.batch_forest)

    def _grow_batch(self, capacity: int) -> None:
        import warp as wp

        dev = self._device
        self.batch_row = wp.zeros(capacity, dtype=wp.int32, device=dev)
        self.batch_out = wp.zeros((capacity, 2), dtype=wp.float32, device=dev)

    def _collide_paper(self, particles, r_max: float) -> None:
        import warp as wp

        from kernels.collide import PaperArgs, launch_count_detected, launch_paper_update

        det = self.detector
        n_pairs = det.detect(particles, r_max)  # also leaves the hash grid of the current positions
        if not n_pairs:
            return
        launch_count_detected(n_pairs, det.pair_i, det.pair_j, particles.stream, self.n_streams, self.detected,
                              det.pair_state)
        args = PaperArgs()
        args.grid = det.grid.id
        args.particle_x, args.particle_v = particles.x, particles.v
        args.particle_radius, args.particle_density = particles.radius, particles.density
        args.particle_weight, args.particle_alive = particles.weight, particles.alive
        args.particle_stream, args.max_radius, args.n_streams = particles.stream, float(r_max), self.n_streams
        args.batch_row, args.batch_count = self.paper_batch_row, self.batch_count
        launch_paper_update(args, self.forest, self.paper_features, self.v_out, self.calls,
                            batch_forest=self.batch_forest, batch_out=self.paper_batch_out)
        wp.copy(particles.v, self.v_out)

    def counts(self) -> dict:
        """Counts of the last :meth:`accelerate` (host read): totals and per stream pair (see the class)."""
        if self._counts is None:
            s = self.n_streams
            if self._device is None:
                detected = calls = np.zeros((s, s), np.int64)
                skipped = rounds = 0
            else:
                detected = self.detected.numpy().reshape(s, s)
                calls = self.calls.numpy().reshape(s, s)
                skipped, rounds = int(self.skipped.numpy()[0]), int(self.rounds.numpy()[0])
            self._counts = {"detected_pairs": int(detected.sum()), "surrogate_calls": int(calls.sum()),
                            "separating_skipped": skipped, "rounds": rounds,
                            **_pair_counts("detected_pairs", detected), **_pair_counts("surrogate_calls", calls)}
        return dict(self._counts)


class DemCollision:
    """``dem`` (CFD-DEM reference): Hertz-Mindlin contacts sub-stepped at the DEM step across the fluid step.

    :meth:`advance` replaces the push. Per fluid step dt:

    1. the solver's push of eq. (4) (``HelSolver.fluid_push``: the implicit drag exchange with the gas,
       buoyancy-corrected gravity, grad p', a_coll = 0) is evaluated into scratch arrays; it records the
       gas's share of the exchange exactly as the push does, so the next gas step receives the same
       momentum; the fluid acceleration ``a_f = (v_push - v)/dt`` is then held over the step;
    2. ``ceil(dt / dt_DEM)`` velocity-Verlet sub-steps (``kernels/integrate.py``) with the Hertz-Mindlin
       contact forces of the persistent contact list (``kernels/contacts.py``; rebuilt at the start of
       every fluid step and whenever a parcel moved more than skin/2) plus ``m a_f``; the DEM step is
       eq. (12) for the smallest live radius (``Material.time_step``), or ``dt_dem`` if smaller.
    Since the sub-steps apply ``a_f`` for exactly dt, each parcel receives the push's fluid impulse
    (the recorded drag impulse plus gravity and grad p'), and contacts are equal and opposite: particles
    + gas momentum balances as with the push. Positions are those of the DEM integration.

    Weight: DEM contacts are between real spheres, so every live parcel must have weight 1.
    Walls: when the solver has walls (``solver.config.walls`` and the geometry's ``solver.shapes``), every
    sub-step adds the Hertz-Mindlin sphere-wall contact against the geometry's SDF
    (``kernels/collide.py`` ``geometry_wall_forces``, the law of ``kernels/walls.py``): the wall is of the
    particle material (E*, G* of the pair), its dashpot gives ``Material.wall_restitution_normal``, friction
    as between particles; the parcel meets the wall with its radius at the DEM resolution. The strategy
    declares ``handles_walls = True``, so ``HelSolver`` skips the point reflection of ``kernels/reflect.py``
    for it (that reflection, applied after the sub-steps, moved parcels onto their neighbours).
    ``counts()``: ``detected_pairs`` (overlapping at the end of the step; per stream pair
    ``detected_pairs_<a>_<b>``), ``surrogate_calls`` (0) and ``dem_substeps``.
    """

    name = "dem"
    has_parcel_memory = True
    """Contact and wall shear histories are per parcel slot: :meth:`permute_parcels` moves them."""
    handles_walls = True
    """``HelSolver.reflect_at_walls`` skips its point reflection: the wall contacts act inside :meth:`advance`."""

    def __init__(self, *, material: Material | None = None, dt_dem: float | None = None, max_speed: float = 20.0,
                 skin: float | None = None, contact_capacity: int = 32, n_streams: int = DEFAULT_STREAMS):
        self.material = material if material is not None else Material()
        if dt_dem is not None:
            require_positive("dt_dem", dt_dem, "s")
        require_positive("max_speed", max_speed, "m/s")
        if skin is not None:
            require_positive("skin", skin, "m")
        if contact_capacity < 1:
            raise ConfigError(f"contact_capacity must be >= 1 (got {contact_capacity})")
        self.dt_dem_max = dt_dem
        self.max_speed = float(max_speed)
        self.skin_setting = skin
        self.contact_capacity = int(contact_capacity)
        self.n_streams = int(n_streams)
        self._capacity = None
        self._particles = None
        self._counts = None
        self.substeps = 0
        self.dt_dem = None
        self._shapes = None
        self._params()

    def _params(self) -> None:
        from hel_warp.dem import contact_params, damping_for
        from kernels.hertz import MODEL_HERTZ, ContactParams

        m = self.material
        E, nu = m.youngs_modulus, m.poisson_ratio
        self.params = ContactParams()
        self.params.model = MODEL_HERTZ
        self.params.youngs_eff = 1.0 / (2.0 * (1.0 - nu**2) / E)
        self.params.shear_eff = 1.0 / (4.0 * (2.0 - nu) * (1.0 + nu) / E)
        self.params.normal_damping = damping_for(m.restitution)
        self.params.friction = m.friction
        self.params.tangential_damping = 0.0
        self.params.rolling_friction = m.rolling_friction
        # walls of the particle material; the dashpot gives the wall restitution
        self.wall_params = contact_params(m, m)
        self.wall_params.normal_damping = damping_for(m.wall_restitution_normal)

    def _setup(self, particles) -> None:
        import warp as wp

        from hel_warp.dem import ContactList

        if self._particles is particles:
            return
        n = particles.count
        dev = particles.device
        self._particles = particles
        self._capacity = n
        self.contacts = ContactList.empty(n, self.contact_capacity, dev)
        self._old_contacts = ContactList.empty(n, self.contact_capacity, dev)
        self._spheres, self._rows, self._old_rows = self._kernel_views(particles)
        self.force = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.torque = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.x_at_build = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.rebuild_flag = wp.zeros(1, dtype=wp.int32, device=dev)
        self.overflow = wp.zeros(1, dtype=wp.int32, device=dev)
        self.v_start = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.x_push = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.v_push = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.a_fluid = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.wall_shear = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.grid = wp.HashGrid(128, 128, 128, device=dev)
        self.grid.reserve(n)
        self.detector = _PairDetector(dev, n)
        s2 = self.n_streams * self.n_streams
        self.detected = wp.zeros(s2, dtype=wp.int32, device=dev)
        self.pair_state = None

    def permute_parcels(self, new_to_old, old_to_new) -> None:
        """``HelSolver.sort_parcels`` reordered the parcels: move the contact rows (partners renumbered, shear
        history kept) and the wall shear history with them."""
        import warp as wp

        from kernels import contacts as kc

        if self._capacity is None:
            return
        n = self._capacity
        wp.launch(kc.gather_contact_rows, dim=n, device=self.force.device,
                  inputs=[self.contacts.partner, self.contacts.count, self.contacts.shear, new_to_old, old_to_new],
                  outputs=[self._old_contacts.partner, self._old_contacts.count, self._old_contacts.shear])
        self.contacts.copy_from(self._old_contacts)
        kc.launch_gather(self.wall_shear, new_to_old, self.v_start)
        wp.copy(self.wall_shear, self.v_start)

    def _kernel_views(self, particles):
        """What the kernels/contacts.py and kernels/integrate.py wrappers take: the ``SphereArrays`` /
        ``ContactRows`` struct views where that API exists, else the Particles and ContactList themselves."""
        try:
            from kernels.integrate import sphere_arrays
        except ImportError:
            return particles, self.contacts, self._old_contacts
        return sphere_arrays(particles), self.contacts.rows(), self._old_contacts.rows()

    # ------------------------------------------------------------------ the strategy interface
    def accelerate(self, solver) -> None:
        """No acceleration: the contacts act inside :meth:`advance`."""
        solver.fields.parcel_a_coll.zero_()

    def advance(self, solver) -> None:
        """Replaces the push: fluid acceleration held, DEM sub-steps across ``solver.config.dt``."""
        p = solver.pool.particles
        fields = solver.fields
        self._setup(p)
        walls = bool(getattr(solver.config, "walls", False))
        self._shapes = getattr(solver, "shapes", None) if walls else None
        alive = p.alive.numpy().astype(bool)
        self._counts = None
        if not alive.any():
            self.substeps = 0
            return
        weight = p.weight.numpy()[alive]
        if np.any(weight != 1.0):
            raise ConfigError("the dem collision model needs parcels of weight 1 (real spheres); "
                              f"found weights {np.unique(weight)[:4].tolist()}; inject with weight=1")
        radius = p.radius.numpy()[alive]
        r_min, r_max = float(radius.min()), float(radius.max())
        dt = float(solver.config.dt)
        stable = self.material.time_step(r_min, max_speed=self.max_speed).chosen
        dt_dem = stable if self.dt_dem_max is None else min(stable, self.dt_dem_max)
        n_sub = max(1, int(math.ceil(dt / dt_dem - 1e-9)))
        h = dt / n_sub
        self.dt_dem = h
        self.substeps = n_sub
        skin = self.skin_setting if self.skin_setting is not None else 0.3 * r_max

        # 1. the push's fluid step into scratch arrays: drag impulse recorded as the push does it
        import warp as wp

        from kernels.collide import launch_held_fluid_acceleration

        fields.parcel_a_coll.zero_()
        wp.copy(self.v_start, p.v)
        solver.fluid_push(particle_x_out=self.x_push, particle_v_out=self.v_push)
        launch_held_fluid_acceleration(self.v_start, self.v_push, p.alive, dt, self.a_fluid)

        # 2. DEM sub-steps
        self.simulate(p, n_sub, h, r_max, skin)
        self._count_overlaps(p, r_max)

    def simulate(self, particles, n_sub: int, h: float, r_max: float, skin: float) -> None:
        """``n_sub`` velocity-Verlet steps of ``h`` with contacts + the held ``a_fluid`` (no gravity term)."""
        import warp as wp

        from kernels.contacts import launch_flag_rebuild
        from kernels.integrate import launch_kick, launch_kick_drift

        self._setup(particles)
        zero = wp.vec3(0.0, 0.0, 0.0)
        self._rebuild(particles, r_max, skin)
        self._forces(particles, h)

        def rebuild():
            self._rebuild(particles, r_max, skin)

        spheres = self._spheres
        for _ in range(n_sub):
            launch_kick_drift(spheres, self.force, self.torque, zero, h)
            self.rebuild_flag.zero_()
            launch_flag_rebuild(spheres, self.x_at_build, 0.5 * skin, self.rebuild_flag)
            wp.capture_if(self.rebuild_flag, on_true=rebuild)
            self._forces(particles, h)
            launch_kick(spheres, self.force, self.torque, zero, h)
        if int(self.overflow.numpy()[0]) > 0:
            raise ConfigError(f"a parcel had {int(self.overflow.numpy()[0])} contact candidates, more than "
                              f"contact_capacity = {self.contact_capacity}; raise contact_capacity")

    def _rebuild(self, particles, r_max: float, skin: float) -> None:
        from kernels.contacts import launch_build_contact_list

        self.grid.build(particles.x, 2.0 * r_max + skin)
        self._old_contacts.copy_from(self.contacts)
        launch_build_contact_list(self.grid, self._spheres, r_max, skin, self._old_rows, self._rows,
                                  self.x_at_build, self.overflow)

    def _forces(self, particles, h: float) -> None:
        from kernels.collide import launch_add_fluid_force
        from kernels.contacts import launch_contact_forces

        launch_contact_forces(self._spheres, self._rows, self.params, h, self.force, self.torque)
        launch_add_fluid_force(self.a_fluid, particles.radius, particles.density, self.force)
        if self._shapes is not None:
            from kernels.collide import launch_geometry_wall_forces

            launch_geometry_wall_forces(self._spheres, self._shapes, self.wall_params, h, self.wall_shear,
                                        self.force, self.torque)

    def _count_overlaps(self, particles, r_max: float) -> None:
        from kernels.collide import launch_count_detected

        self.detected.zero_()
        n_pairs = self.detector.detect(particles, r_max)
        launch_count_detected(n_pairs, self.detector.pair_i, self.detector.pair_j, particles.stream,
                              self.n_streams, self.detected, self.detector.pair_state)

    def counts(self) -> dict:
        """Overlapping pairs at the end of the last step (also per stream pair) and the DEM sub-steps."""
        if self._counts is None:
            s = self.n_streams
            detected = (self.detected.numpy().reshape(s, s) if self._capacity is not None
                        else np.zeros((s, s), np.int64))
            self._counts = {"detected_pairs": int(detected.sum()), "surrogate_calls": 0,
                            "dem_substeps": int(self.substeps), **_pair_counts("detected_pairs", detected)}
        return dict(self._counts)


class SurrogatePaperCollision(SurrogateCollision):
    """``surrogate-paper``: :class:`SurrogateCollision` in ``paper`` mode (a ``paper``-form model)."""

    def __init__(self, *, model_dir: str, n_streams: int = DEFAULT_STREAMS):
        super().__init__(model_dir=model_dir, mode="paper", n_streams=n_streams)


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
