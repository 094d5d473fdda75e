"""Pair bookkeeping shared by the collision strategies: overlap detection on a hash grid, per-stream-pair counts."""

from __future__ import annotations

import numpy as np

DEFAULT_STREAMS = 4
"""Stream tags counted separately (tags outside [0, n_streams) count as the nearest end)."""


def pair_counts(prefix: str, matrix: np.ndarray) -> dict:
    """{"<prefix>_<a>_<b>": count} for every stream pair a <= b of an (S, S) upper-triangular count matrix.

    Every pair is listed (zeros too), so the keys are the same at every step (one column each in the run
    output)."""
    s = matrix.shape[0]
    return {f"{prefix}_{a}_{b}": int(matrix[a, b]) for a in range(s) for b in range(a, s)}


class PairDetector:
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
