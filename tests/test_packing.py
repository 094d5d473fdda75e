"""The poured beds of ``hel_warp.case.packing`` against the random packings of spheres: frictional spheres poured
into a box come to rest in a loose random packing, frictionless ones pour towards random close packing (Onoda &
Liniger 1990: 0.555-0.60 loose; Scott & Kilgour 1969: 0.637 close), and no two spheres overlap."""

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from hel_warp import case as hc
from hel_warp.case import packing
from hel_warp.gas.grid import Box

D = 1.2e-3
SIDE = 12e-3
COUNT = 900


def below(z, centre, r):
    """Volume of each sphere below the plane at height z: a spherical cap, pi h^2 (3 r - h) / 3."""
    h = np.clip(z - (centre - r), 0.0, 2.0 * r)
    return math.pi * h * h * (3.0 * r - h) / 3.0


def bulk_fraction(bed) -> float:
    """Solids fraction of the bed between two diameters above the floor and three below its surface, over the
    whole cross-section (the wall layers included, which lower it below the bulk's): each sphere's volume in the
    slab exactly."""
    x, r = bed["x"], bed["radius"]
    top = float(np.max(x[:, 2] + r))
    z1, z2 = 2.0 * D, top - 3.0 * D
    return float(np.sum(below(z2, x[:, 2], r) - below(z1, x[:, 2], r)) / (SIDE * SIDE * (z2 - z1)))


@pytest.fixture(scope="module")
def beds(tmp_path_factory):
    """The same 900 spheres poured loose and dense, in a cache of their own."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("HEL_WARP_CACHE", str(tmp_path_factory.mktemp("pour_cache")))
        flow = hc.Flow("column", lo=(0, 0, 0), hi=(SIDE, SIDE, 40e-3), spacing=2.4e-3, gravity=(0, 0, -9.81))
        material = hc.Material(density=1000.0, youngs_modulus=1.2e8, poisson_ratio=0.3, restitution=0.986,
                               friction=0.3)
        species = flow.species("beads", D, material=material)
        region = Box(lo=(0.0, 0.0, 0.0), hi=(SIDE, SIDE, 40e-3))
        return {dense: packing.poured_bed(species, region, COUNT, (0.0, 0.0, -9.81), 3, dense=dense)
                for dense in (False, True)}


def test_frictional_spheres_pour_loose_and_frictionless_ones_dense(beds):
    # glass-like spheres (mu = 0.3) pack loose, the frictionless pour towards random close packing; the wall
    # layers of this 10-diameter column lower both by a few hundredths, and nothing packs beyond 0.64 at random
    loose, dense = bulk_fraction(beds[False]), bulk_fraction(beds[True])
    assert 0.50 <= loose <= 0.60, loose
    assert 0.59 <= dense <= 0.64, dense
    assert dense > loose + 0.03, (loose, dense)
    assert beds[True]["height"] < beds[False]["height"]
    # the whole bed's fraction (surface included) is below the slab's
    assert beds[True]["solids_fraction"] < dense and beds[False]["solids_fraction"] < loose


def hertz_deflection(force, material, radius):
    """Overlap of two equal Hertz spheres pressed by ``force``: F = 4/3 E* sqrt(R*) delta^1.5, E* = E / (2 (1 -
    nu^2)), R* = R / 2 (Johnson 1985)."""
    e_star = material.youngs_modulus / (2.0 * (1.0 - material.poisson_ratio**2))
    return (3.0 * force / (4.0 * e_star * math.sqrt(0.5 * radius))) ** (2.0 / 3.0)


@pytest.mark.parametrize("dense", [False, True])
def test_a_poured_bed_keeps_every_sphere_and_only_the_pours_weight_deflection(beds, dense):
    """Every sphere kept, inside the walls; what overlap is left is the pour's soft spheres' deformation under the
    bed's weight: below the Hertz deflection (at the pour's modulus) of a contact carrying five times the weight of
    the column of spheres above the floor (force chains carry several times the mean load)."""
    bed = beds[dense]
    x, r = bed["x"], bed["radius"]
    assert len(x) == COUNT
    mass = 1000.0 * math.pi / 6.0 * D**3
    layers = bed["height"] / D
    soft = hc.Material(youngs_modulus=packing.POUR_MODULUS, poisson_ratio=0.3)
    bound = hertz_deflection(5.0 * layers * mass * 9.81, soft, 0.5 * D)
    pairs = cKDTree(x).query_pairs(r=2.0 * float(r.max()), output_type="ndarray")
    gap = np.linalg.norm(x[pairs[:, 0]] - x[pairs[:, 1]], axis=1) - r[pairs[:, 0]] - r[pairs[:, 1]]
    assert -gap.min() < bound, (-gap.min(), bound)
    assert np.all(x[:, :2] - r[:, None] >= -bound) and np.all(x[:, :2] + r[:, None] <= SIDE + bound)
    assert np.all(x[:, 2] - r >= -bound)
