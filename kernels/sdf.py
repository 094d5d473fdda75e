"""Analytic signed distance of the flow geometry: a union of (possibly rotated) boxes and capped cylinders.

Sign convention: **negative inside the fluid**, positive in the solid, zero on the wall.

One shape is an oriented box with centre ``c``, rotation ``R`` (rows = the box's local
axes in world coordinates, so ``p_local = R (p - c)``) and half extents ``b``. An
axis-aligned box has ``R = I``; an inclined channel of rectangular cross-section along a
direction ``d`` is a box whose first local axis is ``d``.

Box distance (exact, Quilez, "distance functions", 2D/3D box):
    q = |p_local| - b,  d = |max(q, 0)| + min(max(q_x, q_y, q_z), 0).
Its gradient (the unit normal, pointing from the fluid into the wall) is
``sign(p) max(q,0)/|max(q,0)|`` outside and ``sign(p_a) e_a`` (a = argmax q) inside,
rotated back to world axes with ``R^T``.

A capped cylinder (``kind`` 1) uses the same frame: its axis is the first local axis, ``b = (half length,
radius, radius)``; with ``q = (|p_x| - b_x, sqrt(p_y^2 + p_z^2) - b_y)`` its exact distance is
``|max(q, 0)| + min(max(q_0, q_1), 0)`` (Quilez, "capped cylinder").

Union: ``d = min_i d_i``; exact outside the union and on its zero level set. Inside, ``|d|``
is a lower bound of the distance to the wall (exact away from the junctions where shapes
overlap: near an opening into another shape it reports the wall of the shape the point is
deepest in). The normal is that of the minimising shape.

Wall code of other rooms calls ``sdf_union`` / ``sdf_union_normal`` with an ``SdfShapes``
built once by ``hel_warp.gas.grid.Geometry.shapes_struct``.
"""

import warp as wp


@wp.struct
class SdfShapes:
    """Oriented boxes and cylinders of the geometry (arrays of length ``count``)."""

    center: wp.array(dtype=wp.vec3)
    """Shape centres, m."""
    rotation: wp.array(dtype=wp.mat33)
    """Rows are the shape's local axes in world coordinates (orthonormal)."""
    half_extent: wp.array(dtype=wp.vec3)
    """Half sizes along the local axes, m (a cylinder: half length, radius, radius)."""
    kind: wp.array(dtype=wp.int32)
    """SHAPE_BOX or SHAPE_CYLINDER."""
    count: int


SHAPE_BOX = wp.constant(0)
SHAPE_CYLINDER = wp.constant(1)


@wp.func
def sdf_box(p_local: wp.vec3, half: wp.vec3):
    """Exact signed distance of an axis-aligned box centred at the origin (negative inside)."""
    q = wp.vec3(wp.abs(p_local[0]) - half[0], wp.abs(p_local[1]) - half[1], wp.abs(p_local[2]) - half[2])
    outside = wp.length(wp.vec3(wp.max(q[0], 0.0), wp.max(q[1], 0.0), wp.max(q[2], 0.0)))
    inside = wp.min(wp.max(q[0], wp.max(q[1], q[2])), 0.0)
    return outside + inside


@wp.func
def _sign(x: float):
    if x < 0.0:
        return -1.0
    return 1.0


@wp.func
def sdf_box_gradient(p_local: wp.vec3, half: wp.vec3):
    """Unit gradient of ``sdf_box`` in the box frame (points from inside towards outside)."""
    q = wp.vec3(wp.abs(p_local[0]) - half[0], wp.abs(p_local[1]) - half[1], wp.abs(p_local[2]) - half[2])
    s = wp.vec3(_sign(p_local[0]), _sign(p_local[1]), _sign(p_local[2]))
    qp = wp.vec3(wp.max(q[0], 0.0), wp.max(q[1], 0.0), wp.max(q[2], 0.0))
    length = wp.length(qp)
    if length > 0.0:
        return wp.cw_mul(s, qp) / length
    if q[0] >= q[1] and q[0] >= q[2]:
        return wp.vec3(s[0], 0.0, 0.0)
    if q[1] >= q[2]:
        return wp.vec3(0.0, s[1], 0.0)
    return wp.vec3(0.0, 0.0, s[2])


@wp.func
def sdf_cylinder(p_local: wp.vec3, half: wp.vec3):
    """Exact signed distance of a capped cylinder along the local x axis centred at the origin (negative inside)."""
    rho = wp.sqrt(p_local[1] * p_local[1] + p_local[2] * p_local[2])
    qx = wp.abs(p_local[0]) - half[0]
    qr = rho - half[1]
    outside = wp.sqrt(wp.max(qx, 0.0) * wp.max(qx, 0.0) + wp.max(qr, 0.0) * wp.max(qr, 0.0))
    return outside + wp.min(wp.max(qx, qr), 0.0)


@wp.func
def sdf_cylinder_gradient(p_local: wp.vec3, half: wp.vec3):
    """Unit gradient of ``sdf_cylinder`` in the cylinder frame (points from inside towards outside)."""
    rho = wp.sqrt(p_local[1] * p_local[1] + p_local[2] * p_local[2])
    radial = wp.vec3(0.0, 1.0, 0.0)
    if rho > 0.0:
        radial = wp.vec3(0.0, p_local[1] / rho, p_local[2] / rho)
    axial = wp.vec3(_sign(p_local[0]), 0.0, 0.0)
    qx = wp.abs(p_local[0]) - half[0]
    qr = rho - half[1]
    if qx > 0.0 or qr > 0.0:
        g = axial * wp.max(qx, 0.0) + radial * wp.max(qr, 0.0)
        return g / wp.length(g)
    if qx >= qr:
        return axial
    return radial


@wp.func
def sdf_oriented_box(p: wp.vec3, center: wp.vec3, rotation: wp.mat33, half: wp.vec3):
    """Signed distance of a rotated box (see the module docstring for ``rotation``)."""
    return sdf_box(rotation * (p - center), half)


@wp.func
def sdf_shape(shapes: SdfShapes, s: int, p: wp.vec3):
    """Signed distance of shape ``s`` of the union (a box or a capped cylinder)."""
    p_local = shapes.rotation[s] * (p - shapes.center[s])
    if shapes.kind[s] == SHAPE_CYLINDER:
        return sdf_cylinder(p_local, shapes.half_extent[s])
    return sdf_box(p_local, shapes.half_extent[s])


@wp.func
def sdf_union(shapes: SdfShapes, p: wp.vec3):
    """Signed distance of the union of all shapes, ``min_i d_i`` (negative inside the fluid)."""
    d = float(1.0e30)
    for s in range(shapes.count):
        d = wp.min(d, sdf_shape(shapes, s, p))
    return d


@wp.func
def sdf_union_normal(shapes: SdfShapes, p: wp.vec3):
    """Unit wall normal at ``p`` pointing out of the fluid (gradient of the minimising shape)."""
    d = float(1.0e30)
    best = int(0)
    for s in range(shapes.count):
        ds = sdf_shape(shapes, s, p)
        if ds < d:
            d = ds
            best = s
    rotation = shapes.rotation[best]
    p_local = rotation * (p - shapes.center[best])
    n_local = sdf_box_gradient(p_local, shapes.half_extent[best])
    if shapes.kind[best] == SHAPE_CYLINDER:
        n_local = sdf_cylinder_gradient(p_local, shapes.half_extent[best])
    return wp.transpose(rotation) * n_local


@wp.kernel
def sdf_points_kernel(
    shapes: SdfShapes,
    points: wp.array(dtype=wp.vec3),
    # outputs
    distance: wp.array(dtype=float),
    normal: wp.array(dtype=wp.vec3),
):
    tid = wp.tid()
    distance[tid] = sdf_union(shapes, points[tid])
    normal[tid] = sdf_union_normal(shapes, points[tid])


@wp.kernel
def fluid_mask_kernel(
    shapes: SdfShapes,
    origin: wp.vec3,
    spacing: float,
    # outputs
    cell_fluid: wp.array3d(dtype=wp.int32),
):
    i, j, k = wp.tid()
    centre = origin + spacing * wp.vec3(float(i) + 0.5, float(j) + 0.5, float(k) + 0.5)
    if sdf_union(shapes, centre) < 0.0:
        cell_fluid[i, j, k] = 1
    else:
        cell_fluid[i, j, k] = 0


def eval_sdf(shapes: SdfShapes, points, distance, normal) -> None:
    """Signed distance and unit normal at ``points`` (vec3 array) into the given output arrays."""
    wp.launch(sdf_points_kernel, dim=points.shape[0], inputs=[shapes, points],
              outputs=[distance, normal], device=points.device)


def eval_fluid_mask(shapes: SdfShapes, origin, spacing: float, cell_fluid) -> None:
    """``cell_fluid[i,j,k] = 1`` where the SDF at the cell centre is < 0, else 0."""
    wp.launch(fluid_mask_kernel, dim=cell_fluid.shape, inputs=[shapes, wp.vec3(origin), float(spacing)],
              outputs=[cell_fluid], device=cell_fluid.device)
