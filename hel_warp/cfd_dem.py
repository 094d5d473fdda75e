"""Collision strategy ``dem``: the CFD-DEM reference (Hertz-Mindlin contacts sub-stepped across the fluid step).

Follows the strategy interface of ``hel_warp.hel`` (``name``, ``accelerate``, ``advance``, ``counts``,
``permute_parcels``, ``handles_walls``). Contacts: ``kernels/contacts.py``, ``kernels/hertz.py``; integration:
``kernels/integrate.py`` (velocity Verlet, the held fluid force); SDF walls: ``kernels/walls.py``.
"""

from __future__ import annotations

import math

import numpy as np

from hel_warp.pairs import DEFAULT_STREAMS, PairDetector, pair_counts
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
        self.detector = PairDetector(dev, n)
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

        from kernels.integrate import launch_held_fluid_acceleration

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
        from kernels.integrate import launch_add_fluid_force
        from kernels.contacts import launch_contact_forces

        launch_contact_forces(self._spheres, self._rows, self.params, h, self.force, self.torque)
        launch_add_fluid_force(self.a_fluid, particles.radius, particles.density, self.force)
        if self._shapes is not None:
            from kernels.walls import launch_geometry_wall_forces

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
                            "dem_substeps": int(self.substeps), **pair_counts("detected_pairs", detected)}
        return dict(self._counts)
