"""Collision strategy ``dem``: the CFD-DEM reference (Hertz-Mindlin contacts sub-stepped across the fluid step).

Follows the strategy interface of ``hel_warp.hel`` (``name``, ``accelerate``, ``advance``, ``counts``,
``permute_parcels``, ``handles_walls``). Contacts: ``kernels/contacts.py``, ``kernels/hertz.py``; integration:
``kernels/integrate.py`` (velocity Verlet, the held fluid force); SDF walls: ``kernels/walls.py``.
"""

from __future__ import annotations

import math

import numpy as np

from hel_warp.collisions.pairs import DEFAULT_STREAMS, pair_counts
from hel_warp.errors import ConfigError, require_positive
from hel_warp.material import Material


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
    (``kernels/walls.py`` ``geometry_wall_forces``, the law of ``kernels/walls.py``): the wall is of the
    particle material (E*, G* of the pair), its dashpot gives ``Material.wall_restitution_normal``, friction
    as between particles; the parcel meets the wall with its radius at the DEM resolution. The strategy
    declares ``handles_walls = True``, so ``HelSolver`` skips the point reflection of ``kernels/reflect.py``
    for it (that reflection, applied after the sub-steps, moved parcels onto their neighbours).
    Collisions: the force evaluation after every drift counts contact onsets — a pair whose overlap became
    > 0 while it was not touching at the previous sub-step (``kernels/contacts.py``: a touching flag per
    contact, carried through list rebuilds and parcel sorts, so a lasting contact is counted once and a pair
    that bounces apart and touches again twice) — per stream pair, with the impact speed of each, the normal
    approach speed ``(v_i - v_j) . n`` at the half-step velocities just before contact (no contact force had
    acted on the pair). Contacts already closed at the start of a step are not onsets.

    ``counts()`` (the last step): ``collisions`` (onsets, i.e. real binary collisions) and per stream pair
    a <= b ``collisions_<a>_<b>``; ``impact_speed_sum`` (m/s, float64 sum of the onsets' impact speeds:
    the mean is ``impact_speed_sum / collisions``); ``detected_pairs`` (overlapping at the end of the step;
    per stream pair ``detected_pairs_<a>_<b>``); ``surrogate_calls`` (0); ``dem_substeps``.
    :meth:`onset_events` / :meth:`onset_speeds`: every onset of the last step (particle ids, impact speed,
    time within the step).

    Triply periodic box (``periodic_box=(Lx, Ly, Lz)``, origin 0): contacts found and computed across the
    faces with the minimum-image separation, positions wrapped into [0, L) at every list rebuild and at the
    end of the step; each axis must hold 3 contact-search cells (2 r_max + skin). :meth:`advance_free` moves
    the particles by dt with contacts only (no gas, no gravity, no walls): the homogeneous-cooling case.

    ``particle_contacts=False``: no particle-particle forces (and no onsets); walls act as before — the
    reference for how much of a result the walls alone make. ``detected_pairs`` still counts the overlaps.
    """

    name = "dem"
    has_parcel_memory = True
    """Contact and wall shear histories are per parcel slot: :meth:`permute_parcels` moves them."""
    handles_walls = True
    """``HelSolver.reflect_at_walls`` skips its point reflection: the wall contacts act inside :meth:`advance`."""

    GRID_CELLS_MAX = 128
    """Hash-grid cells per axis at most (a periodic box with more search cells gets larger cells)."""

    def __init__(self, *, material: Material | None = None, dt_dem: float | None = None, max_speed: float = 20.0,
                 skin: float | None = None, contact_capacity: int = 32, n_streams: int = DEFAULT_STREAMS,
                 periodic_box: tuple[float, float, float] | None = None, particle_contacts: bool = True,
                 onset_events: int | None = None):
        """``periodic_box``: (Lx, Ly, Lz), m, a triply periodic box with origin 0 (None: open space).
        ``particle_contacts``: False switches the particle-particle contacts off (walls kept).
        ``onset_events``: entries of the per-step onset list (None: grows to fit, from max(1024, N); 0: none)."""
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
        if periodic_box is not None:
            box = tuple(periodic_box)
            if len(box) != 3:
                raise ConfigError(f"periodic_box must be three lengths (Lx, Ly, Lz) in m (got {periodic_box!r})")
            for axis, length in zip("xyz", box):
                require_positive(f"periodic_box L{axis}", length, "m")
            periodic_box = tuple(float(v) for v in box)
        self.periodic_box = periodic_box
        self.particle_contacts = bool(particle_contacts)
        if onset_events is not None and onset_events < 0:
            raise ConfigError(f"onset_events must be >= 0 or None (got {onset_events})")
        self.onset_events_setting = onset_events
        self._grid_cells = None
        self.box = None
        self._capacity = None
        self._particles = None
        self._counts = None
        self.substeps = 0
        self.dt_dem = None
        self._shapes = None
        self._params()

    def _params(self) -> None:
        from hel_warp.collisions.dem import contact_params, damping_for
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

        from hel_warp.collisions.dem import ContactList, OnsetCounter
        from kernels.contacts import open_space

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
        self.x_grid = wp.zeros(n, dtype=wp.vec3, device=dev) if self.periodic_box is not None else None
        self.box = open_space()
        self._grid_cells = None
        if self.periodic_box is None:
            self.grid = wp.HashGrid(self.GRID_CELLS_MAX, self.GRID_CELLS_MAX, self.GRID_CELLS_MAX, device=dev)
            self.grid.reserve(n)
        s2 = self.n_streams * self.n_streams
        self.detected = wp.zeros(s2, dtype=wp.int32, device=dev)
        events = self.onset_events_setting if self.onset_events_setting is not None else max(1024, n)
        self.onsets = OnsetCounter(particles, self.n_streams, events)
        self.pair_state = None

    def permute_parcels(self, new_to_old, old_to_new) -> None:
        """``HelSolver.sort_parcels`` reordered the parcels: move the contact rows (partners renumbered, shear
        history and touching flags kept) and the wall shear history with them."""
        import warp as wp

        from kernels import contacts as kc

        if self._capacity is None:
            return
        kc.launch_gather_contact_rows(self.contacts.rows(), new_to_old, old_to_new, self._old_contacts.rows())
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
        dt = float(solver.config.dt)
        plan = self._prepare(p, dt)
        if plan is None:
            return
        n_sub, h, r_max, skin = plan

        # 1. the push's fluid step into scratch arrays: drag impulse recorded as the push does it
        import warp as wp

        from kernels.integrate import launch_held_fluid_acceleration

        fields.parcel_a_coll.zero_()
        wp.copy(self.v_start, p.v)
        solver.fluid_push(particle_x_out=self.x_push, particle_v_out=self.v_push)
        launch_held_fluid_acceleration(self.v_start, self.v_push, p.alive, dt, self.a_fluid)

        # 2. DEM sub-steps
        self.simulate(p, n_sub, h, r_max, skin)
        self._finish_step(p, r_max, skin)

    def advance_free(self, particles, dt: float) -> None:
        """Advance ``particles`` (in place) by ``dt`` with the contacts alone: no gas, no gravity, no walls.

        ``ceil(dt / dt_DEM)`` velocity-Verlet sub-steps (the DEM step of :meth:`advance`), particle contacts
        only (minimum image in a periodic box), positions wrapped into [0, L) at the end in a periodic box;
        ``counts()`` updated as for :meth:`advance`. Parcels must have weight 1."""
        require_positive("dt", dt, "s")
        self._setup(particles)
        self._shapes = None
        plan = self._prepare(particles, float(dt))
        if plan is None:
            return
        n_sub, h, r_max, skin = plan
        self.a_fluid.zero_()
        self.simulate(particles, n_sub, h, r_max, skin)
        self._finish_step(particles, r_max, skin)

    def _prepare(self, particles, dt: float):
        """Checks and the sub-step plan ``(n_sub, h, r_max, skin)`` of one fluid step; None without live parcels.
        Zeroes the step's counters."""
        self._counts = None
        self.detected.zero_()
        offered = self.onsets.offered_events
        if self.onset_events_setting is None:
            self.onsets.grow_events(offered)  # the last step's list was too short: room for as many next time
        self.onsets.reset()
        alive = particles.alive.numpy().astype(bool)
        if not alive.any():
            self.substeps = 0
            return None
        weight = particles.weight.numpy()[alive]
        if np.any(weight != 1.0):
            raise ConfigError("the dem collision model needs parcels of weight 1 (real spheres); "
                              f"found weights {np.unique(weight)[:4].tolist()}; inject with weight=1")
        radius = particles.radius.numpy()[alive]
        r_min, r_max = float(radius.min()), float(radius.max())
        stable = self.material.time_step(r_min, max_speed=self.max_speed).chosen
        dt_dem = stable if self.dt_dem_max is None else min(stable, self.dt_dem_max)
        n_sub = max(1, int(math.ceil(dt / dt_dem - 1e-9)))
        h = dt / n_sub
        self.dt_dem = h
        self.substeps = n_sub
        skin = self.skin_setting if self.skin_setting is not None else 0.3 * r_max
        if self.periodic_box is not None:
            self._periodic_grid(particles, 2.0 * r_max + skin)
        return n_sub, h, r_max, skin

    def _periodic_grid(self, particles, search: float) -> None:
        """Hash grid of the periodic box: n_a = floor(L_a / search) cells (<= GRID_CELLS_MAX), at least 3."""
        import warp as wp

        from kernels.contacts import periodic_box

        lengths = self.periodic_box
        short = [(axis, length) for axis, length in zip("xyz", lengths) if length < 3.0 * search]
        if short:
            axis, length = short[0]
            raise ConfigError(f"periodic_box L{axis} = {length:.4g} m is shorter than 3 contact-search cells "
                              f"(3 x (2 r_max + skin) = {3.0 * search:.4g} m); enlarge the box or reduce the skin")
        cells = tuple(min(self.GRID_CELLS_MAX, int(math.floor(length / search * (1.0 + 1e-12))))
                      for length in lengths)
        if cells != self._grid_cells:
            self.grid = wp.HashGrid(*cells, device=particles.device)
            self.grid.reserve(particles.count)
            self._grid_cells = cells
            self.box = periodic_box(lengths, cells)

    def _finish_step(self, particles, r_max: float, skin: float) -> None:
        """Overlapping pairs at the end of the step; positions wrapped into the periodic box."""
        from kernels.contacts import launch_count_touching_stream_pairs, launch_wrap_into_box

        if not self.particle_contacts:
            self._rebuild(particles, r_max, skin)  # the list the overlap count reads (no forces used it)
        launch_count_touching_stream_pairs(self._spheres, self._rows, particles.stream, self.n_streams,
                                           self.detected, box=self.box)
        if self.periodic_box is not None:
            launch_wrap_into_box(self.box, particles.x, self.x_grid)

    def simulate(self, particles, n_sub: int, h: float, r_max: float, skin: float) -> None:
        """``n_sub`` velocity-Verlet steps of ``h`` with contacts + the held ``a_fluid`` (no gravity term).

        Onsets are counted from the first sub-step on (the force evaluation at the start only sets the
        touching flags)."""
        import warp as wp

        from kernels.contacts import launch_flag_rebuild
        from kernels.integrate import launch_kick, launch_kick_drift

        self._setup(particles)
        zero = wp.vec3(0.0, 0.0, 0.0)
        contacts = self.particle_contacts
        if contacts:
            self._rebuild(particles, r_max, skin)
        self.onsets.struct.counting = 0
        self._forces(particles, h)
        self.onsets.struct.counting = 1

        def rebuild():
            self._rebuild(particles, r_max, skin)

        spheres = self._spheres
        for _ in range(n_sub):
            self.onsets.advance_substep()
            launch_kick_drift(spheres, self.force, self.torque, zero, h)
            if contacts:
                self.rebuild_flag.zero_()
                launch_flag_rebuild(spheres, self.x_at_build, 0.5 * skin, self.rebuild_flag)
                wp.capture_if(self.rebuild_flag, on_true=rebuild)
            self._forces(particles, h)
            launch_kick(spheres, self.force, self.torque, zero, h)
        if int(self.overflow.numpy()[0]) > 0:
            raise ConfigError(f"a parcel had {int(self.overflow.numpy()[0])} contact candidates, more than "
                              f"contact_capacity = {self.contact_capacity}; raise contact_capacity")

    def _rebuild(self, particles, r_max: float, skin: float) -> None:
        from kernels.contacts import launch_build_contact_list, launch_wrap_into_box

        if self.periodic_box is not None:
            launch_wrap_into_box(self.box, particles.x, self.x_grid)
            self.grid.build(self.x_grid, 1.0)  # grid coordinates: one cell per unit
        else:
            self.grid.build(particles.x, 2.0 * r_max + skin)
        self._old_contacts.copy_from(self.contacts)
        launch_build_contact_list(self.grid, self._spheres, r_max, skin, self._old_rows, self._rows,
                                  self.x_at_build, self.overflow, box=self.box)

    def _forces(self, particles, h: float) -> None:
        from kernels.integrate import launch_add_fluid_force
        from kernels.contacts import launch_contact_forces

        if self.particle_contacts:
            launch_contact_forces(self._spheres, self._rows, self.params, h, self.force, self.torque, box=self.box,
                                  onsets=self.onsets.struct)
        else:
            self.force.zero_()
            self.torque.zero_()
        launch_add_fluid_force(self.a_fluid, particles.radius, particles.density, self.force)
        if self._shapes is not None:
            from kernels.walls import launch_geometry_wall_forces

            launch_geometry_wall_forces(self._spheres, self._shapes, self.wall_params, h, self.wall_shear,
                                        self.force, self.torque)

    def onset_events(self) -> dict:
        """Every contact onset of the last step, sorted by (time, particle_a, particle_b): host arrays
        ``particle_a`` < ``particle_b`` (particle ids), ``speed`` (impact speed: normal approach speed at
        onset, m/s), ``time`` (s from the start of the step: the sub-step of the force evaluation that found
        the contact), ``stream_a`` <= ``stream_b`` (their stream tags, clamped to [0, n_streams)); ``truncated`` is True when the list was
        full (``onset_events`` set too small; the counts are exact regardless)."""
        if self._capacity is None:
            return {"particle_a": np.zeros(0, np.int32), "particle_b": np.zeros(0, np.int32),
                    "speed": np.zeros(0, np.float32), "time": np.zeros(0), "stream_a": np.zeros(0, np.int32),
                    "stream_b": np.zeros(0, np.int32), "truncated": False}
        ev = self.onsets.events()
        sub = ev.pop("substep")
        return {**ev, "time": sub.astype(np.float64) * float(self.dt_dem or 0.0)}

    def onset_speeds(self) -> np.ndarray:
        """The impact speeds of the last step's onsets, m/s (float32, the order of :meth:`onset_events`)."""
        return self.onset_events()["speed"]

    def counts(self) -> dict:
        """The last step: contact onsets (``collisions``, ``collisions_<a>_<b>``, ``impact_speed_sum``),
        overlapping pairs at its end (``detected_pairs``, ``detected_pairs_<a>_<b>``), ``surrogate_calls`` (0),
        ``dem_substeps``."""
        if self._counts is None:
            s = self.n_streams
            if self._capacity is not None:
                detected = self.detected.numpy().reshape(s, s)
                onsets = self.onsets.totals()
            else:
                detected = np.zeros((s, s), np.int64)
                onsets = {"collisions": 0, **pair_counts("collisions", detected), "impact_speed_sum": 0.0}
            self._counts = {**onsets, "detected_pairs": int(detected.sum()), "surrogate_calls": 0,
                            "dem_substeps": int(self.substeps), **pair_counts("detected_pairs", detected)}
        return dict(self._counts)
