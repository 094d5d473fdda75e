"""Grid and geometry: SDF distance/normal against closed forms, fluid mask, patches, resolution errors."""

import math

import numpy as np
import pytest
import warp as wp

from hel_warp.errors import ConfigError
from hel_warp.gas.grid import Box, Channel, Geometry, Grid, Patch
from kernels import gas as gas_kernels
from kernels import sdf as sdf_kernels


def evaluate(geometry, points):
    shapes = geometry.shapes_struct()
    pts = wp.array(np.asarray(points, dtype=np.float32), dtype=wp.vec3)
    distance = wp.zeros(len(points), dtype=float)
    normal = wp.zeros(len(points), dtype=wp.vec3)
    sdf_kernels.eval_sdf(shapes, pts, distance, normal)
    return distance.numpy().astype(np.float64), normal.numpy().astype(np.float64)


def test_box_distance_and_normal_closed_form():
    """Box [0,2]x[0,1]x[0,1]: face, edge and corner regions outside, depth inside."""
    geometry = Geometry(shapes=(Box(lo=(0, 0, 0), hi=(2, 1, 1)),))
    points = [(3.0, 0.5, 0.5),    # beyond the +x face: d = 1, n = +x
              (-0.5, 0.5, 0.5),   # beyond -x face: d = 0.5, n = -x
              (2.3, 1.4, 0.5),    # beyond the (+x,+y) edge: d = |(0.3, 0.4)| = 0.5
              (-0.3, -0.4, 1.2),  # beyond a corner: d = |(0.3,0.4,0.2)|
              (1.0, 0.5, 0.8),    # inside, nearest wall +z at 0.2
              (0.1, 0.5, 0.5)]    # inside, nearest wall -x at 0.1
    d, n = evaluate(geometry, points)
    expected_d = [1.0, 0.5, 0.5, math.sqrt(0.29), -0.2, -0.1]
    expected_n = [(1, 0, 0), (-1, 0, 0), (0.6, 0.8, 0), np.array([-0.3, -0.4, 0.2]) / math.sqrt(0.29),
                  (0, 0, 1), (-1, 0, 0)]
    assert np.allclose(d, expected_d, atol=1e-6)
    assert np.allclose(n, np.array(expected_n, dtype=float), atol=1e-6)


def test_inclined_channel_closed_form():
    """Channel along (cos t, sin t, 0) from the origin, length L, width w (in-plane), height H.

    A point at axial position s and in-plane offset q from the axis: inside the channel
    (|q| < w/2, 0 < s < L, |z| < H/2) the distance to the nearest wall is
    -min(w/2 - |q|, H/2 - |z|, s, L - s); outside through a side wall it is |q| - w/2 with the
    normal along +-(-sin t, cos t, 0).
    """
    t, length, width, height = math.radians(30.0), 10.0, 2.0, 4.0
    d_axis = np.array([math.cos(t), math.sin(t), 0.0])
    d_perp = np.array([-math.sin(t), math.cos(t), 0.0])
    geometry = Geometry(shapes=(Channel(start=(0, 0, 0), end=tuple(length * d_axis), width=width, height=height),))
    rng = np.random.default_rng(0)
    s = rng.uniform(1.5, length - 1.5, 40)
    q = rng.uniform(-3.0, 3.0, 40)
    z = rng.uniform(-0.5, 0.5, 40)
    points = s[:, None] * d_axis + q[:, None] * d_perp + z[:, None] * np.array([0, 0, 1.0])
    d, n = evaluate(geometry, points)
    inside = np.abs(q) < width / 2
    expected = np.where(inside, -np.minimum(width / 2 - np.abs(q), height / 2 - np.abs(z)), np.abs(q) - width / 2)
    assert np.allclose(d, expected, atol=2e-5)
    expected_n = np.sign(q)[:, None] * d_perp
    assert np.allclose(n, expected_n, atol=1e-5)
    # beyond the end cap, off-axis beyond the side: corner distance in the (s, q) plane
    p = (length + 0.3) * d_axis + (width / 2 + 0.4) * d_perp
    d1, n1 = evaluate(geometry, [p])
    assert d1[0] == pytest.approx(0.5, abs=1e-5)
    assert np.allclose(n1[0], 0.6 * d_axis + 0.8 * d_perp, atol=1e-5)


def test_union_is_min_and_normals_are_unit():
    geometry = Geometry(shapes=(Box(lo=(0, 0, 0), hi=(4, 1, 1)),
                                Channel(start=(2, 0.5, 0.5), end=(2, 5, 0.5), width=1, height=1)))
    rng = np.random.default_rng(1)
    points = rng.uniform(-1, 6, size=(200, 3))
    d, n = evaluate(geometry, points)
    d_box, _ = evaluate(Geometry(shapes=geometry.shapes[:1]), points)
    d_ch, _ = evaluate(Geometry(shapes=geometry.shapes[1:]), points)
    assert np.allclose(d, np.minimum(d_box, d_ch), atol=1e-6)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    # where the union SDF is exact (outside), the normal is the SDF gradient (finite differences)
    eps = 1e-3
    outside = d > 0.05
    fd = np.stack([(evaluate(geometry, points + eps * e)[0] - evaluate(geometry, points - eps * e)[0]) / (2 * eps)
                   for e in np.eye(3)], axis=1)
    assert np.allclose(n[outside], fd[outside], atol=2e-2)


def test_mask_counts_cells_of_aligned_boxes():
    """Boxes aligned with cell faces: the fluid mask holds exactly their cells (T shape)."""
    h = 1e-3
    grid = Grid(spacing=h, shape=(12, 10, 4))
    geometry = Geometry(shapes=(Box(lo=(0, 0, 0), hi=(12e-3, 4e-3, 4e-3)), Box(lo=(4e-3, 3e-3, 0), hi=(8e-3, 10e-3, 4e-3))))
    domain = geometry.build(grid)
    fluid = domain.cell_fluid.numpy()
    assert fluid.sum() == 12 * 4 * 4 + 4 * 6 * 4
    assert fluid[0, 0, 0] == 1 and fluid[0, 9, 0] == 0 and fluid[5, 9, 2] == 1


def test_face_types_and_patches():
    h = 1e-3
    grid = Grid(spacing=h, shape=(12, 10, 4))
    geometry = Geometry(
        shapes=(Box(lo=(-1e-3, 0, 0), hi=(13e-3, 4e-3, 4e-3)), Box(lo=(4e-3, 3e-3, 0), hi=(8e-3, 11e-3, 4e-3))),
        patches=(Patch(name="in", kind="inlet", axis=0, side="min", velocity=(2.0, 0, 0)),
                 Patch(name="side", kind="inlet", axis=1, side="max", velocity=(0, -1.0, 0)),
                 Patch(name="out", kind="outlet", axis=0, side="max", pressure=5.0)))
    domain = geometry.build(grid)
    tx, ty = domain.face_type.x.numpy(), domain.face_type.y.numpy()
    assert (tx[0, :4, :] == int(gas_kernels.FACE_INLET)).all() and (tx[0, 4:, :] == int(gas_kernels.FACE_WALL)).all()
    assert (tx[12, :4, :] == int(gas_kernels.FACE_OUTLET)).all()
    assert (ty[4:8, 10, :] == int(gas_kernels.FACE_INLET)).sum() == 16
    assert domain.patch_faces["side"][1].sum() == 16 and domain.patch_faces["in"][1].sum() == 16
    assert np.allclose(domain.face_bc.pressure.x.numpy()[12, :4, :], 5.0)
    assert np.allclose(domain.face_bc.velocity_x.numpy()[0, :4, :, 0], 2.0)
    # the no-slip walls inside: x-faces between fluid and solid cells are walls
    assert (tx[1:12, 5, :][domain.cell_fluid.numpy()[:11, 5, :] == 0] == int(gas_kernels.FACE_WALL)).all()


def test_periodic_faces_alias():
    grid = Grid(spacing=1.0, shape=(4, 5, 6), periodic=(True, False, True))
    domain = Geometry(shapes=(Box(lo=(-1, -1, -1), hi=(9, 9, 9)),)).build(grid)
    tx, ty, tz = (a.numpy() for a in (domain.face_type.x, domain.face_type.y, domain.face_type.z))
    assert (tx[0] == int(gas_kernels.FACE_FLUID)).all() and (tx[4] == int(gas_kernels.FACE_ALIAS)).all()
    assert (ty[:, 0] == int(gas_kernels.FACE_WALL)).all() and (ty[:, 5] == int(gas_kernels.FACE_WALL)).all()
    assert (tz[..., 6] == int(gas_kernels.FACE_ALIAS)).all()


def test_too_coarse_grid_names_the_spacing():
    grid = Grid(spacing=1e-3, shape=(20, 20, 10))
    geometry = Geometry(shapes=(Channel(start=(0, 0, 5e-3), end=(20e-3, 15e-3, 5e-3), width=2.5e-3, height=8e-3,
                                        name="arm"),))
    with pytest.raises(ConfigError, match=r"'arm'.*use spacing <= 0.0008333"):
        geometry.build(grid)


def test_inlet_without_fluid_names_the_spacing():
    grid = Grid(spacing=1e-3, shape=(10, 10, 4))
    geometry = Geometry(shapes=(Box(lo=(0, 0, 0), hi=(10e-3, 4e-3, 4e-3)),),
                        patches=(Patch(name="in", kind="inlet", axis=0, side="min", lo=(0, 7e-3, 0), hi=(0, 9e-3, 4e-3),
                                       velocity=(1, 0, 0)),
                                 Patch(name="out", kind="outlet", axis=0, side="max")))
    with pytest.raises(ConfigError, match="'in' covers no fluid cell.*use spacing <="):
        geometry.build(grid)


def test_geometry_config_errors():
    with pytest.raises(ConfigError, match="into the domain"):
        Patch(name="in", kind="inlet", axis=0, side="max", velocity=(1, 0, 0))
    with pytest.raises(ConfigError, match="no outlet"):
        Geometry(shapes=(Box(lo=(0, 0, 0), hi=(1, 1, 1)),),
                 patches=(Patch(name="in", kind="inlet", axis=0, side="min", velocity=(1, 0, 0)),)
                 ).build(Grid(spacing=0.1, shape=(10, 10, 10)))
    with pytest.raises(ConfigError, match="periodic"):
        Geometry(shapes=(Box(lo=(0, 0, 0), hi=(1, 1, 1)),),
                 patches=(Patch(name="out", kind="outlet", axis=0, side="min"),)
                 ).build(Grid(spacing=0.1, shape=(10, 10, 10), periodic=(True, False, False)))
    with pytest.raises(ConfigError, match="hi must exceed lo"):
        Box(lo=(0, 0, 0), hi=(1, 0, 1))
