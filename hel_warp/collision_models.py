"""Collision strategies ``surrogate`` (HELSCM, reference paper sec. 4.3) and ``dem`` (CFD-DEM reference).

Both follow the strategy interface of ``hel_warp.hel``: ``name``, ``accelerate(solver)`` (step 4 of
ARCHITECTURE.md "The step", before the push), ``counts()`` (per-step collision counts, a dict), and
for ``dem`` also ``advance(solver)``, which replaces the push.

- :class:`SurrogateCollision` (``mode="pairwise"`` default, ``mode="paper"``): end-of-step detection of
  overlapping parcels on a hash grid, post-collision velocities from the flattened XGBoost forest,
  applied as velocity jumps in ``accelerate`` (``kernels/collide.py`` has the equations and the
  no-double-counting argument).
- :class:`DemCollision` (``hel_warp/cfd_dem.py``, imported here for the name map): Hertz-Mindlin contacts
  sub-stepped at the DEM step of eq. (12) across the fluid step.

Names for the run side: ``hel_warp.hel.collision_model(name, ...)`` resolves ``surrogate``
(:class:`SurrogateCollision`), ``surrogate-paper`` (:class:`SurrogatePaperCollision`) and ``dem``
(:class:`DemCollision`) lazily from here; :data:`STRATEGIES` / :func:`make_collision` are the same map.
"""

from __future__ import annotations

import numpy as np

from hel_warp.errors import ConfigError
from hel_warp.cfd_dem import DemCollision
from hel_warp.pairs import DEFAULT_STREAMS, PairDetector, pair_counts


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
        self.detector = PairDetector(dev, n)
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
                            **pair_counts("detected_pairs", detected), **pair_counts("surrogate_calls", calls)}
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
