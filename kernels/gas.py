"""Kernels of the gas step: eps_f-weighted incompressible flow on a MAC (face-staggered) grid.

Equations (paper eqs. 1-3, constant gas density, no mass source), written per unit volume
of gas after dividing eq. (2) by eps_f with the continuity equation:

    d(eps_f)/dt + div(eps_f u) = 0                                          (1)
    du/dt + (u.grad) u = -grad p'/rho + div(eps_f mu_eff grad u)/(eps_f rho)
                         + S_mom/(eps_f rho)                                (2)

``p' = p - rho g.x`` is the modified pressure (gravity absorbed). The stress of eq. (3) is
kept as ``eps_f mu_eff grad u`` (the transposed-gradient and bulk terms vanish for
constant eps_f mu_eff and a solenoidal u; they are dropped). ``mu_eff = mu + rho nu_t``,
Smagorinsky (1963): ``nu_t = (C_s h)^2 sqrt(2 S:S)``.

Splitting per step (incremental projection, Goda 1979; semi-Lagrangian advection, Stam 1999):
advect (RK2 back-trace, stable at any CFL) -> momentum source, imposed mean pressure gradient
and the old pressure gradient -> implicit (backward-Euler) viscous step, one SPD system per velocity component
-> projection for the increment: ``sum_f eps_f (dp_c - dp_nb) = -(rho h^2/dt) (div(eps_f u*) + d(eps_f)/dt)``.

Layout: face arrays of axis ``a`` have shape ``shape + e_a``; face ``(i,j,k)`` of axis 0 sits
at ``origin + (i, j+1/2, k+1/2) h`` between cells ``i-1`` and ``i``. On a periodic axis the
last face (index ``n_a``) is an alias of face 0 (type ``FACE_ALIAS``), synced after writes.
Linear-solver vectors are flat float64 arrays in ``(i*ny + j)*nz + k`` order.

Launches: every cell and face kernel runs one thread per entry of an index list (``cells`` / ``faces``,
``wp.array(dtype=wp.vec3i)``, built once by ``GasSolver``): the fluid cells and the faces a kernel updates,
not the whole box (on the colliding-streams rig 34,768 of 102,400 cells are fluid). The kernels keep their
branches for solid cells and fixed faces, so a list of the whole box gives the same fields
(``GasSolver(launch_over="box")``, the reference of tests/test_gas.py). Each such kernel is a ``@wp.func``
``<name>_one(..., index)`` for one entry and a ``@wp.kernel`` whose thread runs ``block`` consecutive entries
(``CPU_BLOCK`` on the CPU, 1 on CUDA): Warp's CPU loop copies a kernel's arguments for every thread, ~1 kB
of structs here (``FaceFloat``, ``FaceInt``, ``FaceBc``: ~30 ns per thread, measured), once per block instead.
The entries run in the same order on the CPU, so the fields are the same bits. The face kernels of the step
come as one kernel per face axis (``ADVECT_KERNELS`` and the like, built by ``wp.Kernel`` with the axis a
``wp.static`` constant): the branches of ``get_f`` / ``set_f`` / ``component`` on the axis fold away at compile time.
"""

import warp as wp

# The pressure solver's dot products are float64 atomic sums into a few scalars: on CUDA their order follows the
# thread schedule, so that a HEL run and its restart drifted apart by ~1e-13 in the pressure (seen on an H200). Warp's
# deterministic atomics order them (each thread's record sorted and reduced after the kernel; CUDA only: the CPU runs
# kernels/gas_cpu.py's native loops in index order).
if hasattr(wp.config, "DeterministicMode"):
    wp.set_module_options({"deterministic": wp.config.DeterministicMode.RUN_TO_RUN})

CPU_BLOCK = 64
"""Index-list entries per thread of the cell and face kernels on the CPU (module docstring, "Launches"; 64-256
measured alike on the former ``face_forces_kernel``: 65 -> 33-35 ns per face)."""

FACE_WALL = wp.constant(0)
"""Fixed zero normal velocity (solid neighbour cell or domain wall)."""
FACE_FLUID = wp.constant(1)
"""Interior face between two fluid cells: solved."""
FACE_INLET = wp.constant(2)
"""Fixed velocity from the inlet patch."""
FACE_OUTLET = wp.constant(3)
"""Boundary face with a fixed pressure on its outer side: solved."""
FACE_ALIAS = wp.constant(4)
"""Last face of a periodic axis, a copy of face 0."""


@wp.struct
class GridInfo:
    origin: wp.vec3
    spacing: float
    shape: wp.vec3i
    periodic: wp.vec3i


@wp.struct
class FaceFloat:
    """One float32 array per face axis."""

    x: wp.array3d(dtype=float)
    y: wp.array3d(dtype=float)
    z: wp.array3d(dtype=float)


@wp.struct
class FaceInt:
    x: wp.array3d(dtype=wp.int32)
    y: wp.array3d(dtype=wp.int32)
    z: wp.array3d(dtype=wp.int32)


@wp.struct
class FaceBc:
    """Boundary data of the faces: inlet velocity vector (m/s) and outlet pressure (Pa)."""

    velocity_x: wp.array3d(dtype=wp.vec3)
    velocity_y: wp.array3d(dtype=wp.vec3)
    velocity_z: wp.array3d(dtype=wp.vec3)
    pressure: FaceFloat


@wp.struct
class FlowParams:
    rho: float
    """Gas density, kg/m^3."""
    mu: float
    """Molecular dynamic viscosity, Pa s."""
    smagorinsky: float
    """Smagorinsky constant C_s."""
    eps_min: float
    """Lower clip of eps_f (1 - packing limit)."""
    body_accel: wp.vec3
    """-(imposed mean pressure gradient)/rho, m/s^2."""
    dt: float


@wp.struct
class Stencil:
    """A 7-point system row by row: (A x)_r = diag[r] x_r - sum_m coef[r, m] x[neighbour[r, m]], slots
    m = -x, +x, -y, +y, -z, +z (an unused slot has coef 0 and points at r itself). Box-sized as the
    assembly kernels write it, or compact (the solved rows, ``gather_system_kernel``)."""

    diag: wp.array(dtype=wp.float64)
    coef: wp.array2d(dtype=wp.float64)
    neighbour: wp.array2d(dtype=wp.int32)


def make_stencil(diag, coef, neighbour) -> Stencil:
    A = Stencil()
    A.diag, A.coef, A.neighbour = diag, coef, neighbour
    return A


# ----------------------------------------------------------------- index functions


@wp.func
def unit(axis: int):
    """e_axis, built from comparisons (an element write at a run-time index keeps the vector in memory: ~20 ns per
    face kernel thread on the CPU)."""
    return wp.vec3i(int(axis == 0), int(axis == 1), int(axis == 2))


@wp.func
def unit_f(axis: int):
    """e_axis as a float vector (``unit``'s comparisons): adding ``c * unit_f(axis)`` changes one component exactly
    as an element update would, without a write at a run-time index."""
    return wp.vec3(float(axis == 0), float(axis == 1), float(axis == 2))


@wp.func
def component(v: wp.vec3, axis: int):
    """v[axis] by branches (a read at a run-time index keeps the vector in memory)."""
    if axis == 0:
        return v[0]
    if axis == 1:
        return v[1]
    return v[2]


@wp.func
def wrap_cell(g: GridInfo, c: wp.vec3i):
    """Canonical cell index, or x = -1 when outside a non-periodic boundary."""
    out = c
    for d in range(3):
        n = g.shape[d]
        if c[d] < 0 or c[d] >= n:
            if g.periodic[d] != 0:
                out[d] = (c[d] % n + n) % n
            else:
                return wp.vec3i(-1, 0, 0)
    return out


@wp.func
def wrap_face(g: GridInfo, axis: int, f: wp.vec3i):
    """Canonical face index of axis ``axis`` (alias -> 0), or x = -1 when outside."""
    out = f
    for d in range(3):
        n = g.shape[d]
        upper = n
        if d == axis and g.periodic[d] == 0:
            upper = n + 1
        if f[d] < 0 or f[d] >= upper:
            if g.periodic[d] != 0:
                out[d] = (f[d] % n + n) % n
            else:
                return wp.vec3i(-1, 0, 0)
    return out


@wp.func
def flat_index(shape: wp.vec3i, c: wp.vec3i):
    return (c[0] * shape[1] + c[1]) * shape[2] + c[2]


@wp.func
def face_shape(g: GridInfo, axis: int):
    return g.shape + unit(axis)


@wp.func
def get_f(a: FaceFloat, axis: int, f: wp.vec3i):
    if axis == 0:
        return a.x[f[0], f[1], f[2]]
    if axis == 1:
        return a.y[f[0], f[1], f[2]]
    return a.z[f[0], f[1], f[2]]


@wp.func
def set_f(a: FaceFloat, axis: int, f: wp.vec3i, value: float):
    if axis == 0:
        a.x[f[0], f[1], f[2]] = value
    elif axis == 1:
        a.y[f[0], f[1], f[2]] = value
    else:
        a.z[f[0], f[1], f[2]] = value


@wp.func
def get_t(a: FaceInt, axis: int, f: wp.vec3i):
    if axis == 0:
        return a.x[f[0], f[1], f[2]]
    if axis == 1:
        return a.y[f[0], f[1], f[2]]
    return a.z[f[0], f[1], f[2]]


@wp.func
def get_bc_velocity(bc: FaceBc, axis: int, f: wp.vec3i):
    if axis == 0:
        return bc.velocity_x[f[0], f[1], f[2]]
    if axis == 1:
        return bc.velocity_y[f[0], f[1], f[2]]
    return bc.velocity_z[f[0], f[1], f[2]]


@wp.func
def is_solved(t: int):
    return t == FACE_FLUID or t == FACE_OUTLET


# ----------------------------------------------------------------- sampling (advection)


@wp.func
def sample_axis(g: GridInfo, axis: int, component: int, s: float):
    """Lower and upper sample index along ``axis`` (wrapped on a periodic axis, else clamped to the cells, or to
    the faces for the component normal to ``axis``; ``component`` -1: cells) and the weight of the upper one, at
    grid coordinate ``s``."""
    fl = wp.floor(s)
    lo = int(fl)
    hi = lo + 1
    n = g.shape[axis]
    if g.periodic[axis] != 0:
        lo = (lo % n + n) % n
        hi = (hi % n + n) % n
    else:
        upper = n - 1
        if axis == component:
            upper = n
        lo = wp.clamp(lo, 0, upper)
        hi = wp.clamp(hi, 0, upper)
    return lo, hi, s - fl


@wp.func
def trilinear(values: wp.array3d(dtype=float), i0: int, i1: int, wx: float, j0: int, j1: int, wy: float, k0: int,
              k1: int, wz: float):
    """Trilinear interpolation between the 8 samples at (i0|i1, j0|j1, k0|k1) with upper weights wx, wy, wz: the
    corners summed in the order (x, y, z bits) 000, 100, 010, ..., 111, each weight a product in x, y, z order."""
    ux, uy, uz = 1.0 - wx, 1.0 - wy, 1.0 - wz
    result = float(0.0)
    result = result + ux * uy * uz * values[i0, j0, k0]
    result = result + wx * uy * uz * values[i1, j0, k0]
    result = result + ux * wy * uz * values[i0, j1, k0]
    result = result + wx * wy * uz * values[i1, j1, k0]
    result = result + ux * uy * wz * values[i0, j0, k1]
    result = result + wx * uy * wz * values[i1, j0, k1]
    result = result + ux * wy * wz * values[i0, j1, k1]
    result = result + wx * wy * wz * values[i1, j1, k1]
    return result


@wp.func
def sample_array(g: GridInfo, values: wp.array3d(dtype=float), component: int, x: wp.vec3):
    """Trilinear value at ``x`` of the face array ``values`` of ``component`` (clamped / wrapped at the box)."""
    s = (x - g.origin) / g.spacing - wp.vec3(0.5, 0.5, 0.5)
    s = s + 0.5 * unit_f(component)
    i0, i1, wx = sample_axis(g, 0, component, s[0])
    j0, j1, wy = sample_axis(g, 1, component, s[1])
    k0, k1, wz = sample_axis(g, 2, component, s[2])
    return trilinear(values, i0, i1, wx, j0, j1, wy, k0, k1, wz)


@wp.func
def sample_component(g: GridInfo, vel: FaceFloat, axis: int, x: wp.vec3):
    """Trilinear value of face component ``axis`` at ``x`` (``sample_array``)."""
    if axis == 0:
        return sample_array(g, vel.x, 0, x)
    if axis == 1:
        return sample_array(g, vel.y, 1, x)
    return sample_array(g, vel.z, 2, x)


@wp.func
def sample_velocity(g: GridInfo, vel: FaceFloat, x: wp.vec3):
    """The three components at ``x`` (``sample_array`` of each): the grid coordinates, and the cell-centred index
    pair of an axis that two components share, computed once."""
    s = (x - g.origin) / g.spacing - wp.vec3(0.5, 0.5, 0.5)
    ci0, ci1, cwx = sample_axis(g, 0, -1, s[0])
    cj0, cj1, cwy = sample_axis(g, 1, -1, s[1])
    ck0, ck1, cwz = sample_axis(g, 2, -1, s[2])
    fi0, fi1, fwx = sample_axis(g, 0, 0, s[0] + 0.5)
    fj0, fj1, fwy = sample_axis(g, 1, 1, s[1] + 0.5)
    fk0, fk1, fwz = sample_axis(g, 2, 2, s[2] + 0.5)
    return wp.vec3(trilinear(vel.x, fi0, fi1, fwx, cj0, cj1, cwy, ck0, ck1, cwz),
                   trilinear(vel.y, ci0, ci1, cwx, fj0, fj1, fwy, ck0, ck1, cwz),
                   trilinear(vel.z, ci0, ci1, cwx, cj0, cj1, cwy, fk0, fk1, fwz))


@wp.func
def neighbour_pair(g: GridInfo, axis: int, lo: int, upper: int):
    """Indices (lo, lo + 1) along ``axis``, wrapped on a periodic axis, else clamped to [0, upper] (``sample_axis``'s
    rule at an integer grid coordinate)."""
    hi = lo + 1
    if g.periodic[axis] != 0:
        n = g.shape[axis]
        return (lo % n + n) % n, (hi % n + n) % n
    return wp.clamp(lo, 0, upper), wp.clamp(hi, 0, upper)


@wp.func
def velocity_at_face(g: GridInfo, vel: FaceFloat, axis: int, f: wp.vec3i):
    """The three components at the centre of face ``f`` of ``axis``: ``sample_velocity`` there, whose weights are 0,
    1/2 or 1, i.e. the face's own value and, for each other component, the mean of the four faces of that
    component around it (the cells on either side of ``f`` along ``axis``, the faces on either side of its centre
    along the component's axis; wrapped or clamped as ``sample_axis``). Equal to ``sample_velocity`` at
    ``face_position`` up to the float32 round-off of that position's grid coordinates."""
    i, j, k = f[0], f[1], f[2]
    if axis == 0:
        i0, i1 = neighbour_pair(g, 0, i - 1, g.shape[0] - 1)
        j0, j1 = neighbour_pair(g, 1, j, g.shape[1])
        k0, k1 = neighbour_pair(g, 2, k, g.shape[2])
        return wp.vec3(vel.x[i, j, k],
                       0.25 * ((vel.y[i0, j0, k] + vel.y[i1, j0, k]) + (vel.y[i0, j1, k] + vel.y[i1, j1, k])),
                       0.25 * ((vel.z[i0, j, k0] + vel.z[i1, j, k0]) + (vel.z[i0, j, k1] + vel.z[i1, j, k1])))
    if axis == 1:
        j0, j1 = neighbour_pair(g, 1, j - 1, g.shape[1] - 1)
        i0, i1 = neighbour_pair(g, 0, i, g.shape[0])
        k0, k1 = neighbour_pair(g, 2, k, g.shape[2])
        return wp.vec3(0.25 * ((vel.x[i0, j0, k] + vel.x[i0, j1, k]) + (vel.x[i1, j0, k] + vel.x[i1, j1, k])),
                       vel.y[i, j, k],
                       0.25 * ((vel.z[i, j0, k0] + vel.z[i, j1, k0]) + (vel.z[i, j0, k1] + vel.z[i, j1, k1])))
    k0, k1 = neighbour_pair(g, 2, k - 1, g.shape[2] - 1)
    i0, i1 = neighbour_pair(g, 0, i, g.shape[0])
    j0, j1 = neighbour_pair(g, 1, j, g.shape[1])
    return wp.vec3(0.25 * ((vel.x[i0, j, k0] + vel.x[i0, j, k1]) + (vel.x[i1, j, k0] + vel.x[i1, j, k1])),
                   0.25 * ((vel.y[i, j0, k0] + vel.y[i, j0, k1]) + (vel.y[i, j1, k0] + vel.y[i, j1, k1])),
                   vel.z[i, j, k])


@wp.func
def face_position(g: GridInfo, axis: int, f: wp.vec3i):
    p = wp.vec3(float(f[0]) + 0.5, float(f[1]) + 0.5, float(f[2]) + 0.5) - 0.5 * unit_f(axis)
    return g.origin + g.spacing * p


@wp.func
def advect_one(
    g: GridInfo,
    axis: int,
    faces: wp.array(dtype=wp.vec3i),
    types: FaceInt,
    vel_old: FaceFloat,
    dt: float,
    vel_new: FaceFloat,
    index: int,
):
    """Semi-Lagrangian advection with an RK2 (midpoint) back-trace; fixed faces keep their value. The first stage
    takes the velocity at the face from the face and its neighbours (``velocity_at_face``), the other two sample
    trilinearly."""
    f = faces[index]
    t = get_t(types, axis, f)
    if is_solved(t):
        x = face_position(g, axis, f)
        x_mid = x - 0.5 * dt * velocity_at_face(g, vel_old, axis, f)
        x_dep = x - dt * sample_velocity(g, vel_old, x_mid)
        set_f(vel_new, axis, f, sample_component(g, vel_old, axis, x_dep))
    else:
        set_f(vel_new, axis, f, get_f(vel_old, axis, f))


def per_axis_kernels(make, module_name: str):
    """One kernel per face axis (x, y, z): ``make(axis)`` returns the kernel function with the axis a ``wp.static``
    constant; the kernels are keyed ``<function name>_<axis letter>`` in module ``module_name``."""
    kernels = []
    for axis in range(3):
        function = make(axis)
        kernels.append(wp.Kernel(function, key=f"{function.__name__}_{'xyz'[axis]}",
                                 module=wp.get_module(module_name)))
    return tuple(kernels)


def _advect_kernel(axis_constant: int):
    def advect_kernel(
        block: int,
        g: GridInfo,
        faces: wp.array(dtype=wp.vec3i),
        types: FaceInt,
        vel_old: FaceFloat,
        dt: float,
        # outputs
        vel_new: FaceFloat,
    ):
        """``advect_one`` for ``block`` consecutive entries of ``faces`` per thread (module docstring, "Launches"),
        the face axis a compile-time constant."""
        t = wp.tid()
        for index in range(t * block, wp.min(faces.shape[0], (t + 1) * block)):
            advect_one(g, wp.static(axis_constant), faces, types, vel_old, dt, vel_new, index)

    return advect_kernel


ADVECT_KERNELS = per_axis_kernels(_advect_kernel, __name__)
"""``advect_one``'s kernel per face axis (x, y, z): with the axis known when the kernel is compiled, its branches on
the axis (which face array, which component) fold away (~11 % of the advection on the rig, the same numbers)."""


# ----------------------------------------------------------------- cell quantities


@wp.func
def eps_f_one(
    cells: wp.array(dtype=wp.vec3i),
    cell_eps_s: wp.array3d(dtype=float),
    cell_fluid: wp.array3d(dtype=wp.int32),
    eps_min: float,
    cell_eps_f: wp.array3d(dtype=float),
    index: int,
):
    """eps_f = max(1 - eps_s, eps_min) in fluid cells, 1 in solid cells."""
    c = cells[index]
    i, j, k = c[0], c[1], c[2]
    if cell_fluid[i, j, k] != 0:
        cell_eps_f[i, j, k] = wp.clamp(1.0 - cell_eps_s[i, j, k], eps_min, 1.0)
    else:
        cell_eps_f[i, j, k] = 1.0


@wp.kernel
def eps_f_kernel(
    block: int,
    cells: wp.array(dtype=wp.vec3i),
    cell_eps_s: wp.array3d(dtype=float),
    cell_fluid: wp.array3d(dtype=wp.int32),
    eps_min: float,
    # outputs
    cell_eps_f: wp.array3d(dtype=float),
):
    """``eps_f_one`` for ``block`` consecutive entries of ``cells`` per thread (module
    docstring, "Launches")."""
    t = wp.tid()
    for index in range(t * block, wp.min(cells.shape[0], (t + 1) * block)):
        eps_f_one(cells, cell_eps_s, cell_fluid, eps_min, cell_eps_f, index)


@wp.func
def cell_velocity_one(
    g: GridInfo,
    cells: wp.array(dtype=wp.vec3i),
    cell_fluid: wp.array3d(dtype=wp.int32),
    vel: FaceFloat,
    cell_velocity: wp.array3d(dtype=wp.vec3),
    index: int,
):
    """Cell-centred velocity = mean of the two faces per axis (0 in solid cells)."""
    c = cells[index]
    i, j, k = c[0], c[1], c[2]
    u = wp.vec3(0.0, 0.0, 0.0)
    if cell_fluid[i, j, k] != 0:
        for a in range(3):
            hi = wrap_face(g, a, c + unit(a))
            u[a] = 0.5 * (get_f(vel, a, c) + get_f(vel, a, hi))
    cell_velocity[i, j, k] = u


@wp.kernel
def cell_velocity_kernel(
    block: int,
    g: GridInfo,
    cells: wp.array(dtype=wp.vec3i),
    cell_fluid: wp.array3d(dtype=wp.int32),
    vel: FaceFloat,
    # outputs
    cell_velocity: wp.array3d(dtype=wp.vec3),
):
    """``cell_velocity_one`` for ``block`` consecutive entries of ``cells`` per thread (module
    docstring, "Launches")."""
    t = wp.tid()
    for index in range(t * block, wp.min(cells.shape[0], (t + 1) * block)):
        cell_velocity_one(g, cells, cell_fluid, vel, cell_velocity, index)


@wp.kernel
def cell_state_kernel(
    block: int,
    g: GridInfo,
    cells: wp.array(dtype=wp.vec3i),
    cell_eps_s: wp.array3d(dtype=float),
    cell_fluid: wp.array3d(dtype=wp.int32),
    eps_min: float,
    vel: FaceFloat,
    # outputs
    cell_eps_f: wp.array3d(dtype=float),
    cell_velocity: wp.array3d(dtype=wp.vec3),
):
    """``eps_f_one`` and ``cell_velocity_one`` in one pass, ``block`` consecutive entries of ``cells`` per thread
    (module docstring, "Launches")."""
    t = wp.tid()
    for index in range(t * block, wp.min(cells.shape[0], (t + 1) * block)):
        eps_f_one(cells, cell_eps_s, cell_fluid, eps_min, cell_eps_f, index)
        cell_velocity_one(g, cells, cell_fluid, vel, cell_velocity, index)


@wp.func
def cell_value(g: GridInfo, field: wp.array3d(dtype=wp.vec3), c: wp.vec3i, fallback: wp.vec3i):
    w = wrap_cell(g, c)
    if w[0] < 0:
        w = fallback
    return field[w[0], w[1], w[2]]


@wp.func
def smagorinsky_one(
    g: GridInfo,
    params: FlowParams,
    cells: wp.array(dtype=wp.vec3i),
    cell_fluid: wp.array3d(dtype=wp.int32),
    cell_velocity: wp.array3d(dtype=wp.vec3),
    cell_eps_f: wp.array3d(dtype=float),
    cell_nu_t: wp.array3d(dtype=float),
    cell_kappa: wp.array3d(dtype=float),
    index: int,
):
    """nu_t = (C_s h)^2 sqrt(2 S:S) (Smagorinsky 1963), kappa = eps_f (mu + rho nu_t)."""
    c = cells[index]
    i, j, k = c[0], c[1], c[2]
    grad = wp.mat33(0.0)
    for d in range(3):
        up = cell_value(g, cell_velocity, c + unit(d), c)
        down = cell_value(g, cell_velocity, c - unit(d), c)
        du = (up - down) / (2.0 * g.spacing)
        for a in range(3):
            grad[a, d] = du[a]
    strain = 0.5 * (grad + wp.transpose(grad))
    ss = float(0.0)
    for a in range(3):
        for d in range(3):
            ss = ss + strain[a, d] * strain[a, d]
    length = params.smagorinsky * g.spacing
    nu_t = length * length * wp.sqrt(2.0 * ss)
    if cell_fluid[i, j, k] == 0:
        nu_t = 0.0
    cell_nu_t[i, j, k] = nu_t
    cell_kappa[i, j, k] = cell_eps_f[i, j, k] * (params.mu + params.rho * nu_t)


@wp.kernel
def smagorinsky_kernel(
    block: int,
    g: GridInfo,
    params: FlowParams,
    cells: wp.array(dtype=wp.vec3i),
    cell_fluid: wp.array3d(dtype=wp.int32),
    cell_velocity: wp.array3d(dtype=wp.vec3),
    cell_eps_f: wp.array3d(dtype=float),
    # outputs
    cell_nu_t: wp.array3d(dtype=float),
    cell_kappa: wp.array3d(dtype=float),
):
    """``smagorinsky_one`` for ``block`` consecutive entries of ``cells`` per thread (module
    docstring, "Launches")."""
    t = wp.tid()
    for index in range(t * block, wp.min(cells.shape[0], (t + 1) * block)):
        smagorinsky_one(g, params, cells, cell_fluid, cell_velocity, cell_eps_f, cell_nu_t, cell_kappa, index)


@wp.func
def face_coefficients_one(
    g: GridInfo,
    axis: int,
    faces: wp.array(dtype=wp.vec3i),
    cell_fluid: wp.array3d(dtype=wp.int32),
    cell_eps_f: wp.array3d(dtype=float),
    cell_kappa: wp.array3d(dtype=float),
    face_eps: FaceFloat,
    face_kappa: FaceFloat,
    index: int,
):
    """Face eps_f and eps_f mu_eff: mean over the adjacent fluid cells (1 and 0 if none)."""
    f = faces[index]
    eps_sum = float(0.0)
    kappa_sum = float(0.0)
    count = float(0.0)
    for side in range(2):
        c = wrap_cell(g, f - (1 - side) * unit(axis))
        if c[0] >= 0:
            if cell_fluid[c[0], c[1], c[2]] != 0:
                eps_sum = eps_sum + cell_eps_f[c[0], c[1], c[2]]
                kappa_sum = kappa_sum + cell_kappa[c[0], c[1], c[2]]
                count = count + 1.0
    if count > 0.0:
        set_f(face_eps, axis, f, eps_sum / count)
        set_f(face_kappa, axis, f, kappa_sum / count)
    else:
        set_f(face_eps, axis, f, 1.0)
        set_f(face_kappa, axis, f, 0.0)


def _face_coefficients_kernel(axis_constant: int):
    def face_coefficients_kernel(
        block: int,
        g: GridInfo,
        faces: wp.array(dtype=wp.vec3i),
        cell_fluid: wp.array3d(dtype=wp.int32),
        cell_eps_f: wp.array3d(dtype=float),
        cell_kappa: wp.array3d(dtype=float),
        # outputs
        face_eps: FaceFloat,
        face_kappa: FaceFloat,
    ):
        """``face_coefficients_one`` for ``block`` consecutive entries of ``faces`` per thread (module
        docstring, "Launches"), the face axis a compile-time constant."""
        t = wp.tid()
        for index in range(t * block, wp.min(faces.shape[0], (t + 1) * block)):
            face_coefficients_one(g, wp.static(axis_constant), faces, cell_fluid, cell_eps_f, cell_kappa, face_eps,
                                  face_kappa, index)

    return face_coefficients_kernel


FACE_COEFFICIENTS_KERNELS = per_axis_kernels(_face_coefficients_kernel, __name__)
"""``face_coefficients_one``'s kernel per face axis (x, y, z), the axis a compile-time constant (as
``ADVECT_KERNELS``)."""


@wp.kernel
def inlet_face_eps_kernel(axis: int, faces: wp.array(dtype=wp.vec3i), face_eps: FaceFloat):
    """eps_f = 1 on the inlet faces ``faces`` of ``axis``: an inlet brings gas only, so its flux is the patch
    velocity itself, the superficial velocity (CFDEMcoupling's inlets hold voidfraction 1), whatever solids the
    cell beside it holds (the face mean of ``face_coefficients_one`` would take that cell's eps_f)."""
    set_f(face_eps, axis, faces[wp.tid()], 1.0)


@wp.func
def momentum_source_increment(g: GridInfo, axis: int, params: FlowParams, cell_fluid: wp.array3d(dtype=wp.int32),
                              face_eps: FaceFloat, cell_momentum_source: wp.array3d(dtype=wp.vec3), f: wp.vec3i):
    """du_f = dt body_accel + sum_c J_c / (2 rho eps_f V) at a solved face: each cell's impulse J (N s) is split
    evenly over its two faces of this axis, so sum_f rho eps_f V du_f = sum_c J_c where both faces
    are free (periodic or interior); the half on a wall face goes to the wall, as the gas pressure
    would carry it there (a uniform source then gives the uniform grad p = S/eps_f of eq. 2)."""
    volume = g.spacing * g.spacing * g.spacing
    impulse = float(0.0)
    for side in range(2):
        c = wrap_cell(g, f - (1 - side) * unit(axis))
        if c[0] >= 0:
            if cell_fluid[c[0], c[1], c[2]] != 0:
                impulse = impulse + 0.5 * component(cell_momentum_source[c[0], c[1], c[2]], axis)
    return params.dt * component(params.body_accel, axis) + impulse / (params.rho * get_f(face_eps, axis, f) * volume)


@wp.func
def periodic_sync_one(
    g: GridInfo,
    axis: int,
    faces: wp.array(dtype=wp.vec3i),
    vel: FaceFloat,
    index: int,
):
    """Copy face 0 of a periodic axis onto its alias face n_a."""
    f = faces[index]
    if f[axis] == g.shape[axis] and g.periodic[axis] != 0:
        f0 = f
        f0[axis] = 0
        set_f(vel, axis, f, get_f(vel, axis, f0))


@wp.kernel
def periodic_sync_kernel(
    block: int,
    g: GridInfo,
    axis: int,
    faces: wp.array(dtype=wp.vec3i),
    # outputs
    vel: FaceFloat,
):
    """``periodic_sync_one`` for ``block`` consecutive entries of ``faces`` per thread (module
    docstring, "Launches")."""
    t = wp.tid()
    for index in range(t * block, wp.min(faces.shape[0], (t + 1) * block)):
        periodic_sync_one(g, axis, faces, vel, index)


# ----------------------------------------------------------------- implicit viscous step


@wp.func
def viscous_neighbour(g: GridInfo, axis: int, types: FaceInt, bc: FaceBc, f: wp.vec3i, d: int, s: int):
    """Classify the neighbour of face ``f`` (axis ``axis``) in direction ``s e_d``.

    Returns (kind, neighbour face, Dirichlet value, distance factor): kind 0 = zero gradient
    (outlet), 1 = coupled unknown, 2 = Dirichlet value at distance h / factor.
    """
    nb = f + s * unit(d)
    w = wrap_face(g, axis, nb)
    if d == axis:
        if w[0] < 0:
            return 0, f, 0.0, 0.0
        t = get_t(types, axis, w)
        if is_solved(t):
            return 1, w, 0.0, 1.0
        return 2, w, get_bc_velocity(bc, axis, w)[axis], 1.0
    if w[0] < 0:
        # across the domain boundary normal to d: the wall (or patch) lies h/2 away
        side_index = 0
        if s > 0:
            side_index = g.shape[d]
        value = float(0.0)
        count = float(0.0)
        n_outlet = float(0.0)
        for side in range(2):
            c = f - (1 - side) * unit(axis)
            c = wrap_cell(g, c)
            if c[0] >= 0:
                bf = c
                bf[d] = side_index
                t = get_t(types, d, bf)
                if t == FACE_OUTLET:
                    n_outlet = n_outlet + 1.0
                if t == FACE_INLET:
                    value = value + get_bc_velocity(bc, d, bf)[axis]
                count = count + 1.0
        if n_outlet >= count:
            return 0, f, 0.0, 0.0
        return 2, f, value / count, 2.0
    t = get_t(types, axis, w)
    if is_solved(t):
        return 1, w, 0.0, 1.0
    index_along = w[axis]
    if g.periodic[axis] == 0 and (index_along == 0 or index_along == g.shape[axis]):
        return 2, w, get_bc_velocity(bc, axis, w)[axis], 1.0
    return 2, w, 0.0, 2.0


@wp.struct
class ViscousTopology:
    """The fixed part of one viscous system, per row and slot m = -x, +x, -y, +y, -z, +z, from
    ``viscous_neighbour`` once at set-up (``viscous_topology_kernel``)."""

    neighbour_flat: wp.array2d(dtype=wp.int32)
    """Flat index (in the face arrays of the axis) of the coupled neighbour face (kind 1; its kappa is read every
    step), -1 for none. Its row is the stencil's ``neighbour`` entry, written once by ``viscous_topology_kernel``."""
    factor: wp.array2d(dtype=float)
    """Distance factor of a Dirichlet neighbour (kind 2: value at h / factor), 0 for none."""
    value: wp.array2d(dtype=float)
    """Its Dirichlet value, m/s."""


@wp.func
def viscous_topology_one(
    g: GridInfo,
    axis: int,
    faces: wp.array(dtype=wp.vec3i),
    face_row: wp.array(dtype=wp.int32),
    types: FaceInt,
    bc: FaceBc,
    topology: ViscousTopology,
    A: Stencil,
    index: int,
):
    """Classify the six neighbours of every solved face of ``axis`` (``viscous_neighbour``; the face types and
    boundary values are fixed), and write the stencil's neighbour rows, which stay: a coupled neighbour's row
    (its coefficient, a mean of two positive kappa, is never 0), the row itself for an unused slot."""
    f = faces[index]
    shape = face_shape(g, axis)
    row = face_row[flat_index(shape, f)]
    if row < 0:
        return
    for d in range(3):
        for side in range(2):
            m = 2 * d + side
            kind, nb, value, factor = viscous_neighbour(g, axis, types, bc, f, d, 2 * side - 1)
            topology.neighbour_flat[row, m] = -1
            topology.factor[row, m] = 0.0
            topology.value[row, m] = 0.0
            A.coef[row, m] = wp.float64(0.0)
            A.neighbour[row, m] = row
            if kind == 1:
                topology.neighbour_flat[row, m] = flat_index(shape, nb)
                A.neighbour[row, m] = face_row[flat_index(shape, nb)]
            elif kind == 2:
                topology.factor[row, m] = factor
                topology.value[row, m] = value


@wp.kernel
def viscous_topology_kernel(
    block: int,
    g: GridInfo,
    axis: int,
    faces: wp.array(dtype=wp.vec3i),
    face_row: wp.array(dtype=wp.int32),
    types: FaceInt,
    bc: FaceBc,
    # outputs
    topology: ViscousTopology,
    A: Stencil,
):
    """``viscous_topology_one`` for ``block`` consecutive entries of ``faces`` per thread (module
    docstring, "Launches")."""
    t = wp.tid()
    for index in range(t * block, wp.min(faces.shape[0], (t + 1) * block)):
        viscous_topology_one(g, axis, faces, face_row, types, bc, topology, A, index)


@wp.func
def forced_velocity(
    g: GridInfo,
    axis: int,
    params: FlowParams,
    types: FaceInt,
    bc: FaceBc,
    cell_fluid: wp.array3d(dtype=wp.int32),
    face_eps: FaceFloat,
    cell_momentum_source: wp.array3d(dtype=wp.vec3),
    p_old: wp.array(dtype=wp.float64),
    advected: FaceFloat,
    f: wp.vec3i,
):
    """u* = u_adv + du_source - (dt/rho) dp^n/dx_axis at a solved face ``f`` (the particle momentum source and
    imposed mean gradient, ``momentum_source_increment``, then the predictor of the incremental projection, Goda
    1979, so that a steady balance of force and pressure, e.g. a fluidised bed, is a fixed point of the step);
    a fixed face keeps ``advected`` as it is."""
    u = get_f(advected, axis, f)
    t = get_t(types, axis, f)
    if t == FACE_FLUID:
        # an interior face: both cells valid and fluid, found once for the source and the gradient (the same
        # operations as momentum_source_increment and face_pressure_gradient)
        c_lo = wrap_cell(g, f - unit(axis))
        c_hi = wrap_cell(g, f)
        volume = g.spacing * g.spacing * g.spacing
        impulse = float(0.0)
        impulse = impulse + 0.5 * component(cell_momentum_source[c_lo[0], c_lo[1], c_lo[2]], axis)
        impulse = impulse + 0.5 * component(cell_momentum_source[c_hi[0], c_hi[1], c_hi[2]], axis)
        u = u + (params.dt * component(params.body_accel, axis) + impulse / (params.rho * get_f(face_eps, axis, f) * volume))
        gradient = float(p_old[flat_index(g.shape, c_hi)] - p_old[flat_index(g.shape, c_lo)]) / g.spacing
        u = u - params.dt / params.rho * gradient
    elif t == FACE_OUTLET:
        u = u + momentum_source_increment(g, axis, params, cell_fluid, face_eps, cell_momentum_source, f)
        u = u - params.dt / params.rho * face_pressure_gradient(g, types, bc, p_old, 1.0, axis, f)
    return u


@wp.func
def viscous_rhs_one(
    g: GridInfo,
    axis: int,
    params: FlowParams,
    faces: wp.array(dtype=wp.vec3i),
    face_row: wp.array(dtype=wp.int32),
    topology: ViscousTopology,
    types: FaceInt,
    bc: FaceBc,
    cell_fluid: wp.array3d(dtype=wp.int32),
    face_eps: FaceFloat,
    face_kappa: wp.array(dtype=float),
    cell_momentum_source: wp.array3d(dtype=wp.vec3),
    p_old: wp.array(dtype=wp.float64),
    advected: FaceFloat,
    rhs: wp.array(dtype=wp.float64),
    guess: wp.array(dtype=wp.float64),
    A: Stencil,
    index: int,
):
    """Backward-Euler viscous system of one component: (rho eps/dt) u - div(kappa grad u) = (rho eps/dt) u*,
    u* = ``forced_velocity`` (the advected velocity and the forces, formed here where the system needs it: no
    pass of its own over the faces), as a 7-point stencil (diag, coef; the neighbour rows stay as
    ``viscous_topology_kernel`` wrote them) for ``stencil_matvec_kernel``, written straight into the
    compact system: row ``face_row[flat face index]`` (-1: a fixed face, no row; see "compacted systems").
    Neighbours as ``topology`` classified them: coupled (coef = mean kappa / h^2), Dirichlet (kappa_f factor /
    h^2 on the diagonal, times the value on the right), or zero gradient (nothing). ``face_kappa``: the kappa of
    this axis's faces as a flat array (``GasField.face_kappa_flat``)."""
    f = faces[index]
    shape = face_shape(g, axis)
    flat = flat_index(shape, f)
    row = face_row[flat]
    if row < 0:
        return
    u_star = forced_velocity(g, axis, params, types, bc, cell_fluid, face_eps, cell_momentum_source, p_old, advected, f)
    guess[row] = wp.float64(u_star)
    h2 = g.spacing * g.spacing
    mass = params.rho * get_f(face_eps, axis, f) / params.dt
    kappa_f = face_kappa[flat]
    b = mass * u_star
    a_diag = mass
    for m in range(6):
        coef = float(0.0)
        neighbour_flat = topology.neighbour_flat[row, m]
        if neighbour_flat >= 0:
            coef = 0.5 * (kappa_f + face_kappa[neighbour_flat]) / h2
            a_diag = a_diag + coef
        else:
            factor = topology.factor[row, m]  # read where there is no coupling only (near walls and outlets)
            if factor > 0.0:
                a_diag = a_diag + factor * kappa_f / h2
                b = b + factor * kappa_f * topology.value[row, m] / h2
        A.coef[row, m] = wp.float64(coef)
    rhs[row] = wp.float64(b)
    A.diag[row] = wp.float64(a_diag)


def _viscous_rhs_kernel(axis_constant: int):
    def viscous_rhs_kernel(
        block: int,
        g: GridInfo,
        params: FlowParams,
        faces: wp.array(dtype=wp.vec3i),
        face_row: wp.array(dtype=wp.int32),
        topology: ViscousTopology,
        types: FaceInt,
        bc: FaceBc,
        cell_fluid: wp.array3d(dtype=wp.int32),
        face_eps: FaceFloat,
        face_kappa: wp.array(dtype=float),
        cell_momentum_source: wp.array3d(dtype=wp.vec3),
        p_old: wp.array(dtype=wp.float64),
        advected: FaceFloat,
        # outputs
        rhs: wp.array(dtype=wp.float64),
        guess: wp.array(dtype=wp.float64),
        A: Stencil,
    ):
        """``viscous_rhs_one`` for ``block`` consecutive entries of ``faces`` per thread (module
        docstring, "Launches"), the face axis a compile-time constant."""
        t = wp.tid()
        for index in range(t * block, wp.min(faces.shape[0], (t + 1) * block)):
            viscous_rhs_one(g, wp.static(axis_constant), params, faces, face_row, topology, types, bc, cell_fluid,
                            face_eps, face_kappa, cell_momentum_source, p_old, advected, rhs, guess, A, index)

    return viscous_rhs_kernel


VISCOUS_RHS_KERNELS = per_axis_kernels(_viscous_rhs_kernel, __name__)
"""``viscous_rhs_one``'s kernel per face axis (x, y, z), the axis a compile-time constant (as
``ADVECT_KERNELS``)."""


@wp.func
def store_component_one(
    g: GridInfo,
    axis: int,
    faces: wp.array(dtype=wp.vec3i),
    face_row: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.float64),
    vel: FaceFloat,
    index: int,
):
    """u_f = x[row of f] on the solved faces (the viscous solution; fixed faces keep their value)."""
    f = faces[index]
    row = face_row[flat_index(face_shape(g, axis), f)]
    if row >= 0:
        set_f(vel, axis, f, float(x[row]))


def _store_component_kernel(axis_constant: int):
    def store_component_kernel(
        block: int,
        g: GridInfo,
        faces: wp.array(dtype=wp.vec3i),
        face_row: wp.array(dtype=wp.int32),
        x: wp.array(dtype=wp.float64),
        # outputs
        vel: FaceFloat,
    ):
        """``store_component_one`` for ``block`` consecutive entries of ``faces`` per thread (module
        docstring, "Launches"), the face axis a compile-time constant."""
        t = wp.tid()
        for index in range(t * block, wp.min(faces.shape[0], (t + 1) * block)):
            store_component_one(g, wp.static(axis_constant), faces, face_row, x, vel, index)

    return store_component_kernel


STORE_COMPONENT_KERNELS = per_axis_kernels(_store_component_kernel, __name__)
"""``store_component_one``'s kernel per face axis (x, y, z), the axis a compile-time constant (as
``ADVECT_KERNELS``)."""


# ----------------------------------------------------------------- pressure projection


@wp.func
def pressure_rhs_one(
    g: GridInfo,
    params: FlowParams,
    cells: wp.array(dtype=wp.vec3i),
    cell_row: wp.array(dtype=wp.int32),
    cell_fluid: wp.array3d(dtype=wp.int32),
    types: FaceInt,
    bc: FaceBc,
    face_eps: FaceFloat,
    vel: FaceFloat,
    cell_eps_f: wp.array3d(dtype=float),
    cell_eps_f_prev: wp.array3d(dtype=float),
    outlet_weight: float,
    rhs: wp.array(dtype=wp.float64),
    A: Stencil,
    active: wp.array(dtype=wp.int32),
    fluid_sum: wp.array(dtype=wp.float64),
    index: int,
):
    """b_c = -(rho h^2/dt)(div(eps u*) + d eps/dt) + sum_outlet 2 eps_f p_out; and the matrix
    (A p)_c = diag_c p_c - sum_m coef_cm p_nb(c,m): diag = sum_fluid eps_f + sum_outlet 2 eps_f,
    coef = eps_f on the 6 faces (0 on walls, inlets, outlets); written straight into the compact system,
    row ``cell_row[flat cell index]`` (-1: a solid cell, no row); the neighbour rows stay as
    ``pressure_neighbours_kernel`` wrote them."""
    c = cells[index]
    i, j, k = c[0], c[1], c[2]
    row = cell_row[flat_index(g.shape, c)]
    if row < 0:
        return
    active[row] = 0
    h = wp.float64(g.spacing)
    div = wp.float64(0.0)
    gross = wp.float64(0.0)
    b = wp.float64(0.0)
    a_diag = wp.float64(0.0)
    for a in range(3):
        for side in range(2):
            f = wrap_face(g, a, c + side * unit(a))
            sign = wp.float64(2 * side - 1)
            eps = wp.float64(get_f(face_eps, a, f))
            flux = eps * wp.float64(get_f(vel, a, f))
            div = div + sign * flux
            gross = gross + wp.abs(flux)
            t = get_t(types, a, f)
            coef = wp.float64(0.0)
            if t == FACE_FLUID and cell_fluid[i, j, k] != 0:
                a_diag = a_diag + eps
                coef = eps
            elif t == FACE_OUTLET:
                a_diag = a_diag + wp.float64(2.0) * eps
                b = b + wp.float64(2.0) * eps * wp.float64(outlet_weight * get_f(bc.pressure, a, f))
            A.coef[row, 2 * a + side] = coef
    div = div / h  # the face fluxes summed first, divided by h once
    gross = gross / h
    d_eps_dt = wp.float64(cell_eps_f[i, j, k] - cell_eps_f_prev[i, j, k]) / wp.float64(params.dt)
    b = b - wp.float64(params.rho) * h * h / wp.float64(params.dt) * (div + d_eps_dt)
    if a_diag == wp.float64(0.0):
        # enclosed fluid cell: nothing can flow, keep p = 0
        rhs[row] = wp.float64(0.0)
        A.diag[row] = wp.float64(1.0)
        return
    rhs[row] = b
    A.diag[row] = a_diag
    active[row] = 1
    wp.atomic_add(fluid_sum, 0, b)
    wp.atomic_add(fluid_sum, 1, wp.float64(1.0))
    gross = wp.float64(params.rho) * h * h / wp.float64(params.dt) * gross
    wp.atomic_add(fluid_sum, 2, gross * gross)


@wp.kernel
def pressure_rhs_kernel(
    block: int,
    g: GridInfo,
    params: FlowParams,
    cells: wp.array(dtype=wp.vec3i),
    cell_row: wp.array(dtype=wp.int32),
    cell_fluid: wp.array3d(dtype=wp.int32),
    types: FaceInt,
    bc: FaceBc,
    face_eps: FaceFloat,
    vel: FaceFloat,
    cell_eps_f: wp.array3d(dtype=float),
    cell_eps_f_prev: wp.array3d(dtype=float),
    outlet_weight: float,
    # outputs
    rhs: wp.array(dtype=wp.float64),
    A: Stencil,
    active: wp.array(dtype=wp.int32),
    fluid_sum: wp.array(dtype=wp.float64),
):
    """``pressure_rhs_one`` for ``block`` consecutive entries of ``cells`` per thread (module
    docstring, "Launches")."""
    t = wp.tid()
    for index in range(t * block, wp.min(cells.shape[0], (t + 1) * block)):
        pressure_rhs_one(g, params, cells, cell_row, cell_fluid, types, bc, face_eps, vel, cell_eps_f,
                  cell_eps_f_prev, outlet_weight, rhs, A, active, fluid_sum, index)


@wp.func
def pressure_neighbours_one(
    g: GridInfo,
    cells: wp.array(dtype=wp.vec3i),
    cell_row: wp.array(dtype=wp.int32),
    cell_fluid: wp.array3d(dtype=wp.int32),
    types: FaceInt,
    A: Stencil,
    index: int,
):
    """The fixed neighbour rows of the pressure system (once, at set-up): across a fluid face of a fluid cell the
    neighbour cell's row (its coefficient eps_f >= eps_min is never 0), else the row itself (an unused slot);
    coefficients 0 until ``pressure_rhs_kernel`` writes them."""
    c = cells[index]
    row = cell_row[flat_index(g.shape, c)]
    if row < 0:
        return
    for a in range(3):
        for side in range(2):
            f = wrap_face(g, a, c + side * unit(a))
            A.coef[row, 2 * a + side] = wp.float64(0.0)
            A.neighbour[row, 2 * a + side] = row
            if get_t(types, a, f) == FACE_FLUID and cell_fluid[c[0], c[1], c[2]] != 0:
                nb = wrap_cell(g, c + (2 * side - 1) * unit(a))
                A.neighbour[row, 2 * a + side] = cell_row[flat_index(g.shape, nb)]


@wp.kernel
def pressure_neighbours_kernel(
    block: int,
    g: GridInfo,
    cells: wp.array(dtype=wp.vec3i),
    cell_row: wp.array(dtype=wp.int32),
    cell_fluid: wp.array3d(dtype=wp.int32),
    types: FaceInt,
    # outputs
    A: Stencil,
):
    """``pressure_neighbours_one`` for ``block`` consecutive entries of ``cells`` per thread (module
    docstring, "Launches")."""
    t = wp.tid()
    for index in range(t * block, wp.min(cells.shape[0], (t + 1) * block)):
        pressure_neighbours_one(g, cells, cell_row, cell_fluid, types, A, index)


@wp.kernel
def remove_mean_kernel(
    active: wp.array(dtype=wp.int32),
    fluid_sum: wp.array(dtype=wp.float64),
    # outputs
    rhs: wp.array(dtype=wp.float64),
):
    """Make the right-hand side of an all-Neumann (no outlet) system compatible: zero mean."""
    row = wp.tid()
    if active[row] != 0:
        rhs[row] = rhs[row] - fluid_sum[0] / fluid_sum[1]


@wp.kernel
def stencil_matvec_kernel(
    A: Stencil,
    x: wp.array(dtype=wp.float64),
    y: wp.array(dtype=wp.float64),
    alpha: wp.float64,
    beta: wp.float64,
    # outputs
    z: wp.array(dtype=wp.float64),
):
    """z = alpha A x + beta y for the 7-point pressure matrix of ``pressure_rhs_kernel``."""
    row = wp.tid()
    ax = A.diag[row] * x[row]
    for m in range(6):
        ax = ax - A.coef[row, m] * x[A.neighbour[row, m]]
    z[row] = alpha * ax + beta * y[row]


@wp.func
def pressure_increment_one(
    g: GridInfo,
    cells: wp.array(dtype=wp.vec3i),
    cell_row: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.float64),
    increment: wp.array(dtype=wp.float64),
    total: wp.array(dtype=wp.float64),
    index: int,
):
    """dp = x[row of c] (flat, box-sized) and p^{n+1} = p^n + dp on the fluid cells (solid cells keep 0)."""
    c = cells[index]
    flat = flat_index(g.shape, c)
    row = cell_row[flat]
    if row >= 0:
        increment[flat] = x[row]
        total[flat] = total[flat] + x[row]


@wp.kernel
def pressure_increment_kernel(
    block: int,
    g: GridInfo,
    cells: wp.array(dtype=wp.vec3i),
    cell_row: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.float64),
    # outputs
    increment: wp.array(dtype=wp.float64),
    total: wp.array(dtype=wp.float64),
):
    """``pressure_increment_one`` for ``block`` consecutive entries of ``cells`` per thread (module
    docstring, "Launches")."""
    t = wp.tid()
    for index in range(t * block, wp.min(cells.shape[0], (t + 1) * block)):
        pressure_increment_one(g, cells, cell_row, x, increment, total, index)


@wp.kernel
def jacobi_kernel(
    diag: wp.array(dtype=wp.float64),
    x: wp.array(dtype=wp.float64),
    y: wp.array(dtype=wp.float64),
    alpha: wp.float64,
    beta: wp.float64,
    # outputs
    z: wp.array(dtype=wp.float64),
):
    """Jacobi preconditioner z = alpha D^-1 x + beta y."""
    row = wp.tid()
    z[row] = alpha * x[row] / diag[row] + beta * y[row]


@wp.func
def face_pressure_gradient(g: GridInfo, types: FaceInt, bc: FaceBc, p: wp.array(dtype=wp.float64),
                           outlet_weight: float, axis: int, f: wp.vec3i):
    """d p / d x_axis at a solved face (Dirichlet outlet pressure ``outlet_weight p_out`` sits on the
    face, h/2 away; weight 0 for a pressure increment)."""
    t = get_t(types, axis, f)
    h = g.spacing
    if t == FACE_FLUID:
        c_lo = wrap_cell(g, f - unit(axis))
        c_hi = wrap_cell(g, f)
        return float(p[flat_index(g.shape, c_hi)] - p[flat_index(g.shape, c_lo)]) / h
    # outlet
    p_out = outlet_weight * get_f(bc.pressure, axis, f)
    if f[axis] == 0:
        return 2.0 * (float(p[flat_index(g.shape, f)]) - p_out) / h
    return 2.0 * (p_out - float(p[flat_index(g.shape, f - unit(axis))])) / h


@wp.func
def face_pressure_gradients(g: GridInfo, types: FaceInt, bc: FaceBc, increment: wp.array(dtype=wp.float64),
                            outlet_weight: float, total: wp.array(dtype=wp.float64), axis: int, f: wp.vec3i):
    """``face_pressure_gradient`` of ``increment`` (outlet weight ``outlet_weight``) and of ``total`` (outlet
    weight 1) at one solved face, the face's type and cells found once: the same two numbers."""
    t = get_t(types, axis, f)
    h = g.spacing
    if t == FACE_FLUID:
        lo = flat_index(g.shape, wrap_cell(g, f - unit(axis)))
        hi = flat_index(g.shape, wrap_cell(g, f))
        return float(increment[hi] - increment[lo]) / h, float(total[hi] - total[lo]) / h
    # outlet
    p_out = get_f(bc.pressure, axis, f)
    increment_out = outlet_weight * p_out
    total_out = 1.0 * p_out
    if f[axis] == 0:
        inside = flat_index(g.shape, f)
        return 2.0 * (float(increment[inside]) - increment_out) / h, 2.0 * (float(total[inside]) - total_out) / h
    inside = flat_index(g.shape, f - unit(axis))
    return 2.0 * (increment_out - float(increment[inside])) / h, 2.0 * (total_out - float(total[inside])) / h


@wp.func
def pressure_correct_one(
    g: GridInfo,
    axis: int,
    params: FlowParams,
    faces: wp.array(dtype=wp.vec3i),
    types: FaceInt,
    bc: FaceBc,
    p: wp.array(dtype=wp.float64),
    outlet_weight: float,
    p_total: wp.array(dtype=wp.float64),
    vel: FaceFloat,
    face_grad_p: FaceFloat,
    index: int,
):
    """u_f = u*_f - (dt/rho) dp/dx_axis on solved faces; and the face gradient of the new pressure ``p_total``
    (outlet weight 1) into ``face_grad_p``, which ``cell_pressure_one`` averages (the same function and values it
    computed itself before: the two cells' pressures are read here anyway)."""
    f = faces[index]
    if is_solved(get_t(types, axis, f)):
        gp, gp_total = face_pressure_gradients(g, types, bc, p, outlet_weight, p_total, axis, f)
        set_f(vel, axis, f, get_f(vel, axis, f) - params.dt / params.rho * gp)
        set_f(face_grad_p, axis, f, gp_total)


def _pressure_correct_kernel(axis_constant: int):
    def pressure_correct_kernel(
        block: int,
        g: GridInfo,
        params: FlowParams,
        faces: wp.array(dtype=wp.vec3i),
        types: FaceInt,
        bc: FaceBc,
        p: wp.array(dtype=wp.float64),
        outlet_weight: float,
        p_total: wp.array(dtype=wp.float64),
        # outputs
        vel: FaceFloat,
        face_grad_p: FaceFloat,
    ):
        """``pressure_correct_one`` for ``block`` consecutive entries of ``faces`` per thread (module
        docstring, "Launches"), the face axis a compile-time constant."""
        t = wp.tid()
        for index in range(t * block, wp.min(faces.shape[0], (t + 1) * block)):
            pressure_correct_one(g, wp.static(axis_constant), params, faces, types, bc, p, outlet_weight, p_total, vel,
                                 face_grad_p, index)

    return pressure_correct_kernel


PRESSURE_CORRECT_KERNELS = per_axis_kernels(_pressure_correct_kernel, __name__)
"""``pressure_correct_one``'s kernel per face axis (x, y, z), the axis a compile-time constant (as
``ADVECT_KERNELS``)."""


@wp.func
def cell_pressure_one(
    g: GridInfo,
    params: FlowParams,
    cells: wp.array(dtype=wp.vec3i),
    cell_fluid: wp.array3d(dtype=wp.int32),
    types: FaceInt,
    face_grad_p: FaceFloat,
    p: wp.array(dtype=wp.float64),
    cell_pressure: wp.array3d(dtype=float),
    cell_grad_p: wp.array3d(dtype=wp.vec3),
    index: int,
):
    """Cell pressure and grad p' = mean of the solved-face gradients (``face_grad_p``, written by
    ``pressure_correct_one``) + imposed mean gradient."""
    c = cells[index]
    i, j, k = c[0], c[1], c[2]
    grad = -params.rho * params.body_accel
    if cell_fluid[i, j, k] != 0:
        for a in range(3):
            acc = float(0.0)
            n = float(0.0)
            for side in range(2):
                f = wrap_face(g, a, c + side * unit(a))
                if is_solved(get_t(types, a, f)):
                    acc = acc + get_f(face_grad_p, a, f)
                    n = n + 1.0
            if n > 0.0:
                grad[a] = grad[a] + acc / n
        cell_pressure[i, j, k] = float(p[flat_index(g.shape, c)])
    else:
        cell_pressure[i, j, k] = 0.0
    cell_grad_p[i, j, k] = grad


@wp.kernel
def cell_pressure_kernel(
    block: int,
    g: GridInfo,
    params: FlowParams,
    cells: wp.array(dtype=wp.vec3i),
    cell_fluid: wp.array3d(dtype=wp.int32),
    types: FaceInt,
    face_grad_p: FaceFloat,
    p: wp.array(dtype=wp.float64),
    # outputs
    cell_pressure: wp.array3d(dtype=float),
    cell_grad_p: wp.array3d(dtype=wp.vec3),
):
    """``cell_pressure_one`` for ``block`` consecutive entries of ``cells`` per thread (module
    docstring, "Launches")."""
    t = wp.tid()
    for index in range(t * block, wp.min(cells.shape[0], (t + 1) * block)):
        cell_pressure_one(g, params, cells, cell_fluid, types, face_grad_p, p, cell_pressure, cell_grad_p, index)


@wp.func
def cell_projected_one(
    g: GridInfo,
    params: FlowParams,
    cells: wp.array(dtype=wp.vec3i),
    cell_fluid: wp.array3d(dtype=wp.int32),
    types: FaceInt,
    face_grad_p: FaceFloat,
    p: wp.array(dtype=wp.float64),
    vel: FaceFloat,
    cell_pressure: wp.array3d(dtype=float),
    cell_grad_p: wp.array3d(dtype=wp.vec3),
    cell_velocity: wp.array3d(dtype=wp.vec3),
    bad_count: wp.array(dtype=wp.int32),
    index: int,
):
    """``cell_pressure_one`` and ``cell_velocity_one`` with each face of the cell found once (the same numbers);
    a cell whose velocity or pressure is not finite adds 1 to ``bad_count[0]``."""
    c = cells[index]
    i, j, k = c[0], c[1], c[2]
    grad = -params.rho * params.body_accel
    u = wp.vec3(0.0, 0.0, 0.0)
    pressure = float(0.0)
    if cell_fluid[i, j, k] != 0:
        for a in range(3):
            hi = wrap_face(g, a, c + unit(a))  # the lower face is c itself
            u[a] = 0.5 * (get_f(vel, a, c) + get_f(vel, a, hi))
            acc = float(0.0)
            n = float(0.0)
            if is_solved(get_t(types, a, c)):
                acc = acc + get_f(face_grad_p, a, c)
                n = n + 1.0
            if is_solved(get_t(types, a, hi)):
                acc = acc + get_f(face_grad_p, a, hi)
                n = n + 1.0
            if n > 0.0:
                grad[a] = grad[a] + acc / n
        pressure = float(p[flat_index(g.shape, c)])
    cell_pressure[i, j, k] = pressure
    cell_grad_p[i, j, k] = grad
    cell_velocity[i, j, k] = u
    if not (wp.isfinite(u) and wp.isfinite(pressure)):
        wp.atomic_add(bad_count, 0, 1)


@wp.kernel
def cell_projected_kernel(
    block: int,
    g: GridInfo,
    params: FlowParams,
    cells: wp.array(dtype=wp.vec3i),
    cell_fluid: wp.array3d(dtype=wp.int32),
    types: FaceInt,
    face_grad_p: FaceFloat,
    p: wp.array(dtype=wp.float64),
    vel: FaceFloat,
    # outputs
    cell_pressure: wp.array3d(dtype=float),
    cell_grad_p: wp.array3d(dtype=wp.vec3),
    cell_velocity: wp.array3d(dtype=wp.vec3),
    bad_count: wp.array(dtype=wp.int32),
):
    """The cell fields after the projection in one pass over ``cells`` (``cell_projected_one``), ``block``
    consecutive entries per thread (module docstring, "Launches"); ``bad_count`` counts cells left non-finite."""
    t = wp.tid()
    for index in range(t * block, wp.min(cells.shape[0], (t + 1) * block)):
        cell_projected_one(g, params, cells, cell_fluid, types, face_grad_p, p, vel, cell_pressure, cell_grad_p,
                           cell_velocity, bad_count, index)


# ----------------------------------------------------------------- compacted systems
# The linear solvers work on the solved rows only: the fluid cells (pressure) and the solved faces of one axis
# (viscous), numbered in ascending box order (``GasSolver``'s ``cell_row`` / ``face_row`` maps: row of a box
# index, -1 for a solid cell or fixed face), so IC(0) sees the same ordering as on the box. The assembly
# kernels write these rows directly; a nonzero coupling always points at another solved row (fluid cell to
# fluid cell, solved face to solved face).


# ----------------------------------------------------------------- aggregation multigrid (pressure)
# A V-cycle preconditioner for the pressure CG (hel_warp/gas/multigrid.py): 2x2x2 blocks of cells aggregate
# into one coarse row, coarse matrices by Galerkin products with the piecewise-constant prolongation
# (A_c = P^T A P, again a 7-point stencil; Braess 1995), multi-colour symmetric Gauss-Seidel smoothing
# (parallel within a colour), a scaled coarse correction.


@wp.kernel
def mg_coarsen_kernel(
    child_start: wp.array(dtype=wp.int32),
    children: wp.array(dtype=wp.int32),
    parent: wp.array(dtype=wp.int32),
    A: Stencil,
    # outputs
    Ac: Stencil,
):
    """Row C of A_c = P^T A P, gathered from its fine rows ``children[child_start[C]:child_start[C+1]]``
    in a fixed order (no atomics: the same sums on any device): a coupling inside the block moves onto
    its diagonal, one to another block adds to the coarse coupling of the same direction (the
    neighbouring block in that direction is unique)."""
    C = wp.tid()
    d = wp.float64(0.0)
    for m in range(6):
        Ac.coef[C, m] = wp.float64(0.0)
        Ac.neighbour[C, m] = C
    for idx in range(child_start[C], child_start[C + 1]):
        r = children[idx]
        d = d + A.diag[r]
        for m in range(6):
            c = A.coef[r, m]
            if c != wp.float64(0.0):
                D = parent[A.neighbour[r, m]]
                if D == C:
                    d = d - c
                else:
                    Ac.coef[C, m] = Ac.coef[C, m] + c
                    Ac.neighbour[C, m] = D
    Ac.diag[C] = d


@wp.func
def gauss_seidel_row(A: Stencil, inverse_diag: wp.array(dtype=wp.float64), b: wp.array(dtype=wp.float64),
                     z: wp.array(dtype=wp.float64), r: int):
    """z_r = (b_r + sum_m coef z_neighbour) / diag_r in place, by the inverse diagonal (``mg_inverse_diagonal_kernel``:
    a division costs ~3 multiplications); a row with diag 0 (inverse 0) is left alone (a block of an all-Neumann
    system can close on itself: A_c = 0)."""
    acc = b[r]
    for m in range(6):
        acc = acc + A.coef[r, m] * z[A.neighbour[r, m]]
    if inverse_diag[r] > wp.float64(0.0):
        z[r] = acc * inverse_diag[r]


@wp.kernel
def mg_inverse_diagonal_kernel(
    A: Stencil,
    # outputs
    inverse_diag: wp.array(dtype=wp.float64),
):
    """1 / diag of a positive diagonal, 0 where the diagonal is 0 (``gauss_seidel_row``)."""
    r = wp.tid()
    inverse_diag[r] = wp.float64(0.0)
    if A.diag[r] > wp.float64(0.0):
        inverse_diag[r] = wp.float64(1.0) / A.diag[r]


@wp.kernel
def mg_smooth_kernel(
    A: Stencil,
    inverse_diag: wp.array(dtype=wp.float64),
    rows: wp.array(dtype=wp.int32),
    b: wp.array(dtype=wp.float64),
    # outputs
    z: wp.array(dtype=wp.float64),
):
    """Gauss-Seidel update of ``rows``, the rows of one colour (no two neighbours share a colour)."""
    gauss_seidel_row(A, inverse_diag, b, z, rows[wp.tid()])


@wp.kernel
def mg_smooth_from_zero_kernel(
    inverse_diag: wp.array(dtype=wp.float64),
    colour: wp.array(dtype=wp.int32),
    b: wp.array(dtype=wp.float64),
    # outputs
    z: wp.array(dtype=wp.float64),
):
    """z = 0, then the Gauss-Seidel update of the rows of colour 0, in one pass over every row: from z = 0 a row
    of colour 0 (whose neighbours are all of other colours) gets b_r / diag_r (0 where diag is 0)."""
    r = wp.tid()
    z[r] = wp.float64(0.0)
    if colour[r] == 0 and inverse_diag[r] > wp.float64(0.0):
        z[r] = b[r] * inverse_diag[r]


@wp.func
def stencil_residual(A: Stencil, b: wp.array(dtype=wp.float64), x: wp.array(dtype=wp.float64), row: int):
    """(b - A x)_row, the arithmetic of ``stencil_matvec_kernel`` with alpha = -1, beta = 1."""
    ax = A.diag[row] * x[row]
    for m in range(6):
        ax = ax - A.coef[row, m] * x[A.neighbour[row, m]]
    return wp.float64(-1.0) * ax + wp.float64(1.0) * b[row]


@wp.kernel
def mg_residual_restrict_kernel(
    child_start: wp.array(dtype=wp.int32),
    children: wp.array(dtype=wp.int32),
    parent: wp.array(dtype=wp.int32),
    A: Stencil,
    b: wp.array(dtype=wp.float64),
    z: wp.array(dtype=wp.float64),
    colour: wp.array(dtype=wp.int32),
    last_colour: int,
    # outputs
    c_b: wp.array(dtype=wp.float64),
):
    """c_b = P^T (b - A z) after a pre-smoothing that ended with the rows of ``last_colour``: the fine residual of
    the block's rows summed in a fixed order (one coarse row per thread; the fine residual is not stored). A row
    of the last colour was just solved for its neighbours' values, so its residual is 0 (up to float64
    round-off) and is not computed, unless Gauss-Seidel left it alone (diag 0). ``parent`` (each fine row's block)
    is for the CPU's native loop (kernels/gas_cpu.py), which streams the fine rows in order and adds each residual
    to its block's sum: the same sums in the same order, as ``children`` lists a block's rows ascending."""
    C = wp.tid()
    acc = wp.float64(0.0)
    for idx in range(child_start[C], child_start[C + 1]):
        r = children[idx]
        if colour[r] != last_colour or not A.diag[r] > wp.float64(0.0):
            acc = acc + stencil_residual(A, b, z, r)
    c_b[C] = acc


@wp.kernel
def mg_prolong_kernel(
    parent: wp.array(dtype=wp.int32),
    c_z: wp.array(dtype=wp.float64),
    scale: wp.float64,
    # outputs
    z: wp.array(dtype=wp.float64),
):
    r = wp.tid()
    z[r] = z[r] + scale * c_z[parent[r]]


@wp.kernel
def mg_coarsest_kernel(
    A: Stencil,
    inverse_diag: wp.array(dtype=wp.float64),
    b: wp.array(dtype=wp.float64),
    n: int,
    sweeps: int,
    # outputs
    z: wp.array(dtype=wp.float64),
):
    """Symmetric Gauss-Seidel sweeps (forward then backward) from z = 0 on the coarsest level, one thread
    (a few dozen rows)."""
    for i in range(n):
        z[i] = wp.float64(0.0)
    for s in range(sweeps):
        for step in range(2 * n):
            i = step
            if step >= n:
                i = 2 * n - 1 - step
            gauss_seidel_row(A, inverse_diag, b, z, i)


# ----------------------------------------------------------------- native Jacobi-PCG (CPU path)
# warp.optim.linear.cg reduces with tile kernels that cost ~0.1 s per dot product on the CPU at
# 1e5 unknowns; this plain PCG (Hestenes & Stiefel 1952; Saad, *Iterative Methods*, alg. 9.1)
# reduces with atomics instead, preconditioned with IC(0) (sequential, fine on the CPU) or Jacobi (the diagonal: no
# factorisation, one streaming pass per iteration with the step and both dot products). Scalars live in ``scalars``: 0 = r.z, 1 = p.Ap, 2 = new r.z, 3 = r.r, 4 = alpha, 5 = beta
# (the two ratios computed once per iteration by one thread, not per row).


DOT_CHUNK = 512
"""Entries one thread of ``pcg_dot_kernel`` (and the other passes with a dot product, their ``chunk`` argument) sums
before its single atomic add on the CPU (the CPU runs the threads one after another: one atomic per entry cost more
than the products)."""
DOT_CHUNK_CUDA = 16
"""The same on a GPU, where a thread's rows run one after another while the other threads run side by side: at 512
the rig's 7,312 pressure rows took 15 threads, and a pass with the matrix product ~0.7 ms on an H200;
at 16, 457 threads (with COARSEST_ROWS_CUDA, one captured PCG iteration went from 0.86 to 0.21 ms and
the rig's step at weight 64 from 67 to 30 ms). The chunks and partial sums fix the order of the additions, so a run repeats to the
bit on one device (the atomics are deterministic) and differs from the CPU's in rounding."""


@wp.kernel
def pcg_dot_kernel(
    a: wp.array(dtype=wp.float64),
    b: wp.array(dtype=wp.float64),
    slot: int,
    chunk: int,
    # outputs
    scalars: wp.array(dtype=wp.float64),
):
    """scalars[slot] += a . b over the chunk [tid * chunk, ...) (launch ceil(n / chunk) threads; ``chunk``:
    DOT_CHUNK on the CPU, DOT_CHUNK_CUDA on a GPU), in four interleaved partial sums (one sum is a chain of dependent adds: ~4x slower on a CPU core)."""
    t = wp.tid()
    first = t * chunk
    last = wp.min(first + chunk, a.shape[0])
    acc0 = wp.float64(0.0)
    acc1 = wp.float64(0.0)
    acc2 = wp.float64(0.0)
    acc3 = wp.float64(0.0)
    quads = first + (last - first) // 4 * 4
    for i in range(first, quads, 4):
        acc0 = acc0 + a[i] * b[i]
        acc1 = acc1 + a[i + 1] * b[i + 1]
        acc2 = acc2 + a[i + 2] * b[i + 2]
        acc3 = acc3 + a[i + 3] * b[i + 3]
    for i in range(quads, last):
        acc0 = acc0 + a[i] * b[i]
    wp.atomic_add(scalars, slot, (acc0 + acc1) + (acc2 + acc3))


@wp.kernel
def pcg_dot_pair_kernel(
    a: wp.array(dtype=wp.float64),
    b: wp.array(dtype=wp.float64),
    slot_ab: int,
    slot_aa: int,
    chunk: int,
    # outputs
    scalars: wp.array(dtype=wp.float64),
):
    """scalars[slot_ab] += a . b and scalars[slot_aa] += a . a in one pass over ``a`` (``pcg_dot_kernel``'s chunks
    and partial sums: the same two numbers)."""
    t = wp.tid()
    first = t * chunk
    last = wp.min(first + chunk, a.shape[0])
    ab0 = wp.float64(0.0)
    ab1 = wp.float64(0.0)
    ab2 = wp.float64(0.0)
    ab3 = wp.float64(0.0)
    aa0 = wp.float64(0.0)
    aa1 = wp.float64(0.0)
    aa2 = wp.float64(0.0)
    aa3 = wp.float64(0.0)
    quads = first + (last - first) // 4 * 4
    for i in range(first, quads, 4):
        ab0 = ab0 + a[i] * b[i]
        ab1 = ab1 + a[i + 1] * b[i + 1]
        ab2 = ab2 + a[i + 2] * b[i + 2]
        ab3 = ab3 + a[i + 3] * b[i + 3]
        aa0 = aa0 + a[i] * a[i]
        aa1 = aa1 + a[i + 1] * a[i + 1]
        aa2 = aa2 + a[i + 2] * a[i + 2]
        aa3 = aa3 + a[i + 3] * a[i + 3]
    for i in range(quads, last):
        ab0 = ab0 + a[i] * b[i]
        aa0 = aa0 + a[i] * a[i]
    wp.atomic_add(scalars, slot_ab, (ab0 + ab1) + (ab2 + ab3))
    wp.atomic_add(scalars, slot_aa, (aa0 + aa1) + (aa2 + aa3))


@wp.func
def stencil_row(A: Stencil, x: wp.array(dtype=wp.float64), row: int):
    """(A x)_row = diag x_row - sum_m coef x_neighbour, in ``stencil_matvec_kernel``'s order."""
    ax = A.diag[row] * x[row]
    for m in range(6):
        ax = ax - A.coef[row, m] * x[A.neighbour[row, m]]
    return ax


@wp.kernel
def pcg_matvec_dot_kernel(
    A: Stencil,
    p: wp.array(dtype=wp.float64),
    slot: int,
    chunk: int,
    # outputs
    ap: wp.array(dtype=wp.float64),
    scalars: wp.array(dtype=wp.float64),
):
    """ap = A p and scalars[slot] += p . ap in one pass over the chunk [tid * chunk, ...) (launch
    ceil(n / chunk) threads): the numbers of ``stencil_matvec_kernel`` (alpha 1, beta 0) then
    ``pcg_dot_kernel`` (the same chunks and four interleaved partial sums), without a second pass over p and ap."""
    t = wp.tid()
    first = t * chunk
    last = wp.min(first + chunk, p.shape[0])
    acc0 = wp.float64(0.0)
    acc1 = wp.float64(0.0)
    acc2 = wp.float64(0.0)
    acc3 = wp.float64(0.0)
    quads = first + (last - first) // 4 * 4
    for i in range(first, quads, 4):
        v0 = stencil_row(A, p, i)
        v1 = stencil_row(A, p, i + 1)
        v2 = stencil_row(A, p, i + 2)
        v3 = stencil_row(A, p, i + 3)
        ap[i] = v0
        ap[i + 1] = v1
        ap[i + 2] = v2
        ap[i + 3] = v3
        acc0 = acc0 + p[i] * v0
        acc1 = acc1 + p[i + 1] * v1
        acc2 = acc2 + p[i + 2] * v2
        acc3 = acc3 + p[i + 3] * v3
    for i in range(quads, last):
        v = stencil_row(A, p, i)
        ap[i] = v
        acc0 = acc0 + p[i] * v
    wp.atomic_add(scalars, slot, (acc0 + acc1) + (acc2 + acc3))


@wp.kernel
def pcg_residual_start_kernel(
    A: Stencil,
    x: wp.array(dtype=wp.float64),
    rhs: wp.array(dtype=wp.float64),
    chunk: int,
    # outputs
    r: wp.array(dtype=wp.float64),
    scalars: wp.array(dtype=wp.float64),
):
    """r = b - A x, scalars[1] += b . b and scalars[3] += r . r over the chunk [tid * chunk, ...) (launch
    ceil(n / chunk) threads): the numbers of ``stencil_matvec_kernel`` (alpha 1, beta 0), the subtraction and two
    ``pcg_dot_kernel`` passes (the same chunks and partial sums) in one pass."""
    t = wp.tid()
    first = t * chunk
    last = wp.min(first + chunk, x.shape[0])
    bb0 = wp.float64(0.0)
    bb1 = wp.float64(0.0)
    bb2 = wp.float64(0.0)
    bb3 = wp.float64(0.0)
    rr0 = wp.float64(0.0)
    rr1 = wp.float64(0.0)
    rr2 = wp.float64(0.0)
    rr3 = wp.float64(0.0)
    quads = first + (last - first) // 4 * 4
    for i in range(first, quads, 4):
        r0 = rhs[i] - stencil_row(A, x, i)
        r1 = rhs[i + 1] - stencil_row(A, x, i + 1)
        r2 = rhs[i + 2] - stencil_row(A, x, i + 2)
        r3 = rhs[i + 3] - stencil_row(A, x, i + 3)
        r[i] = r0
        r[i + 1] = r1
        r[i + 2] = r2
        r[i + 3] = r3
        bb0 = bb0 + rhs[i] * rhs[i]
        bb1 = bb1 + rhs[i + 1] * rhs[i + 1]
        bb2 = bb2 + rhs[i + 2] * rhs[i + 2]
        bb3 = bb3 + rhs[i + 3] * rhs[i + 3]
        rr0 = rr0 + r0 * r0
        rr1 = rr1 + r1 * r1
        rr2 = rr2 + r2 * r2
        rr3 = rr3 + r3 * r3
    for i in range(quads, last):
        ri = rhs[i] - stencil_row(A, x, i)
        r[i] = ri
        bb0 = bb0 + rhs[i] * rhs[i]
        rr0 = rr0 + ri * ri
    wp.atomic_add(scalars, 1, (bb0 + bb1) + (bb2 + bb3))
    wp.atomic_add(scalars, 3, (rr0 + rr1) + (rr2 + rr3))


@wp.kernel
def pcg_step_kernel(
    p: wp.array(dtype=wp.float64),
    ap: wp.array(dtype=wp.float64),
    scalars: wp.array(dtype=wp.float64),
    # outputs
    x: wp.array(dtype=wp.float64),
    r: wp.array(dtype=wp.float64),
):
    """x += alpha p, r -= alpha Ap with alpha = scalars[4] (``pcg_ratio_kernel``)."""
    i = wp.tid()
    alpha = scalars[4]
    x[i] = x[i] + alpha * p[i]
    r[i] = r[i] - alpha * ap[i]


@wp.kernel
def ic0_factor_kernel(
    A: Stencil,
    n: int,
    relaxation: wp.float64,
    # outputs
    pivot: wp.array(dtype=wp.float64),
    pivot_inverse: wp.array(dtype=wp.float64),
):
    """Incomplete Cholesky of the 7-point stencil, A ~ (D + L) D^-1 (D + L^T), one thread (the CPU
    path; the CUDA path keeps Jacobi). IC(0) (``relaxation`` 0): d_i = a_ii - sum_{j<i} a_ij^2 / d_j
    (Meijerink & van der Vorst 1977). Modified IC(0) (``relaxation`` tau in (0, 1]): the fill-in
    a_ij a_jk / d_j that IC(0) drops (k > j, k != i, a neighbour of j) is moved onto the diagonal, times
    tau, so that row sums are kept (Gustafsson 1978; tau = 0.97 as Bridson, *Fluid Simulation for
    Computer Graphics*, 2015, sec. 5.5). A pivot below 1/4 of a_ii falls back to a_ii (IC(0): 1e-3)."""
    floor = wp.float64(1.0e-3)
    if relaxation > wp.float64(0.0):
        floor = wp.float64(0.25)
    for i in range(n):
        d = A.diag[i]
        for m in range(6):
            j = A.neighbour[i, m]
            c = A.coef[i, m]
            if j < i and c != wp.float64(0.0):
                fill = wp.float64(0.0)
                if relaxation > wp.float64(0.0):
                    for m2 in range(6):
                        k = A.neighbour[j, m2]
                        if k > j and k != i:
                            fill = fill + A.coef[j, m2]
                d = d - c * (c + relaxation * fill) / pivot[j]
        if d <= floor * A.diag[i]:
            d = A.diag[i]
        pivot[i] = d
        pivot_inverse[i] = wp.float64(1.0) / d


@wp.kernel
def ic0_apply_kernel(
    pivot_inverse: wp.array(dtype=wp.float64),
    A: Stencil,
    r: wp.array(dtype=wp.float64),
    n: int,
    # outputs
    z: wp.array(dtype=wp.float64),
):
    """z = [(D + L) D^-1 (D + L^T)]^-1 r: forward then backward substitution (one thread), multiplying by the
    inverse pivots (a division in the chain of dependent rows costs ~3x a multiplication). Off-diagonal entries
    of A are -coef."""
    for i in range(n):
        acc = r[i]
        for m in range(6):
            j = A.neighbour[i, m]
            if j < i:
                acc = acc + A.coef[i, m] * z[j]
        z[i] = acc * pivot_inverse[i]
    for step in range(n):
        i = n - 1 - step
        acc = wp.float64(0.0)
        for m in range(6):
            j = A.neighbour[i, m]
            if j > i:
                acc = acc + A.coef[i, m] * z[j]
        z[i] = z[i] + acc * pivot_inverse[i]


@wp.kernel
def ic0_step_apply_kernel(
    pivot_inverse: wp.array(dtype=wp.float64),
    A: Stencil,
    p: wp.array(dtype=wp.float64),
    ap: wp.array(dtype=wp.float64),
    scalars: wp.array(dtype=wp.float64),
    n: int,
    ordered: int,
    # outputs
    x: wp.array(dtype=wp.float64),
    r: wp.array(dtype=wp.float64),
    z: wp.array(dtype=wp.float64),
):
    """``pcg_step_kernel`` (x += alpha p, r -= alpha Ap, alpha = scalars[4]) folded into the forward substitution
    of ``ic0_apply_kernel``, which reads r row by row in the same order: one pass over the rows instead of two,
    the same numbers. ``ordered`` 1: every coupling to a lower row sits in slot 0, 2 or 4 (-x, -y, -z) and to a
    higher row in 1, 3 or 5 (true of the compact systems when no axis is periodic; an unused slot has coef 0 and
    points at the row itself), so the substitutions take those three slots without the index tests: the unused
    slot adds coef 0 times z of its own row, zeroed before the forward row and finite after it."""
    alpha = scalars[4]
    for i in range(n):
        x[i] = x[i] + alpha * p[i]
        r[i] = r[i] - alpha * ap[i]
        acc = r[i]
        if ordered != 0:
            z[i] = wp.float64(0.0)
            acc = acc + A.coef[i, 0] * z[A.neighbour[i, 0]]
            acc = acc + A.coef[i, 2] * z[A.neighbour[i, 2]]
            acc = acc + A.coef[i, 4] * z[A.neighbour[i, 4]]
        else:
            for m in range(6):
                j = A.neighbour[i, m]
                if j < i:
                    acc = acc + A.coef[i, m] * z[j]
        z[i] = acc * pivot_inverse[i]
    for step in range(n):
        i = n - 1 - step
        acc = wp.float64(0.0)
        if ordered != 0:
            acc = acc + A.coef[i, 1] * z[A.neighbour[i, 1]]
            acc = acc + A.coef[i, 3] * z[A.neighbour[i, 3]]
            acc = acc + A.coef[i, 5] * z[A.neighbour[i, 5]]
        else:
            for m in range(6):
                j = A.neighbour[i, m]
                if j > i:
                    acc = acc + A.coef[i, m] * z[j]
        z[i] = z[i] + acc * pivot_inverse[i]


@wp.kernel
def jacobi_start_kernel(
    diag: wp.array(dtype=wp.float64),
    r: wp.array(dtype=wp.float64),
    # outputs
    inverse_diag: wp.array(dtype=wp.float64),
    z: wp.array(dtype=wp.float64),
):
    """The Jacobi preconditioner of the native PCG set up and applied once: inverse_diag = 1 / diag, z = D^-1 r
    (per row; no factorisation)."""
    i = wp.tid()
    inverse = wp.float64(1.0) / diag[i]
    inverse_diag[i] = inverse
    z[i] = r[i] * inverse


@wp.kernel
def jacobi_step_dot_kernel(
    inverse_diag: wp.array(dtype=wp.float64),
    p: wp.array(dtype=wp.float64),
    ap: wp.array(dtype=wp.float64),
    coefficients: wp.array(dtype=wp.float64),
    chunk: int,
    # outputs
    x: wp.array(dtype=wp.float64),
    r: wp.array(dtype=wp.float64),
    z: wp.array(dtype=wp.float64),
    scalars: wp.array(dtype=wp.float64),
):
    """Jacobi-PCG's iteration after A p in one pass over the chunk [tid * chunk, ...) (launch
    ceil(n / chunk) threads): the step x += alpha p, r -= alpha Ap (alpha = coefficients[4],
    ``pcg_step_kernel``), z = D^-1 r, and scalars[2] += r . z, scalars[3] += r . r (``pcg_dot_pair_kernel``'s chunks
    and partial sums): the numbers of those three passes in one. alpha is read from ``coefficients``, the copy
    ``pcg_ratio_kernel`` writes beside ``scalars``: the deterministic atomics (module header) refuse a kernel that
    reads an array it adds to, also through a second argument over the same memory (checked at launch)."""
    t = wp.tid()
    first = t * chunk
    last = wp.min(first + chunk, p.shape[0])
    alpha = coefficients[4]
    rz0 = wp.float64(0.0)
    rz1 = wp.float64(0.0)
    rz2 = wp.float64(0.0)
    rz3 = wp.float64(0.0)
    rr0 = wp.float64(0.0)
    rr1 = wp.float64(0.0)
    rr2 = wp.float64(0.0)
    rr3 = wp.float64(0.0)
    quads = first + (last - first) // 4 * 4
    for i in range(first, quads, 4):
        x[i] = x[i] + alpha * p[i]
        x[i + 1] = x[i + 1] + alpha * p[i + 1]
        x[i + 2] = x[i + 2] + alpha * p[i + 2]
        x[i + 3] = x[i + 3] + alpha * p[i + 3]
        r0 = r[i] - alpha * ap[i]
        r1 = r[i + 1] - alpha * ap[i + 1]
        r2 = r[i + 2] - alpha * ap[i + 2]
        r3 = r[i + 3] - alpha * ap[i + 3]
        r[i] = r0
        r[i + 1] = r1
        r[i + 2] = r2
        r[i + 3] = r3
        z0 = r0 * inverse_diag[i]
        z1 = r1 * inverse_diag[i + 1]
        z2 = r2 * inverse_diag[i + 2]
        z3 = r3 * inverse_diag[i + 3]
        z[i] = z0
        z[i + 1] = z1
        z[i + 2] = z2
        z[i + 3] = z3
        rz0 = rz0 + r0 * z0
        rz1 = rz1 + r1 * z1
        rz2 = rz2 + r2 * z2
        rz3 = rz3 + r3 * z3
        rr0 = rr0 + r0 * r0
        rr1 = rr1 + r1 * r1
        rr2 = rr2 + r2 * r2
        rr3 = rr3 + r3 * r3
    for i in range(quads, last):
        x[i] = x[i] + alpha * p[i]
        ri = r[i] - alpha * ap[i]
        r[i] = ri
        zi = ri * inverse_diag[i]
        z[i] = zi
        rz0 = rz0 + ri * zi
        rr0 = rr0 + ri * ri
    wp.atomic_add(scalars, 2, (rz0 + rz1) + (rz2 + rz3))
    wp.atomic_add(scalars, 3, (rr0 + rr1) + (rr2 + rr3))


# ----------------------------------------------------------------- red-black reduced system (native PCG option)
# A 7-point system whose couplings all join rows of opposite colour (parity of i + j + k; true of a face grid unless a
# periodic axis has an odd count) splits as [[D_b, -N_br], [-N_rb, D_r]] (black, red). Eliminating the red rows
# leaves the Schur complement S = D_b - N_br D_r^-1 N_rb on the black rows (symmetric positive definite), right-hand
# side b_S = b_b + N_br D_r^-1 b_r; x_r = D_r^-1 (b_r + N_rb x_b) after (the "red-black" or "cyclic" reduction,
# Saad, *Iterative Methods*, 2nd ed., sec. 10.4 / 12.3). With x_r from that formula the red rows' residual is 0
# and the black rows' residual is b_S - S x_b, so ||b - A x|| = ||b_S - S x_b||. D_b^-1 S has the eigenvalues
# 1 - mu^2 (mu those of D^-1 N), far better conditioned than D^-1 A: CG on S with the preconditioner D_b^-1
# takes about half the iterations of Jacobi-PCG on A, and an application of S costs one pass over A's rows (the
# red half, then the black half). Colour arrays: ``rows`` the compact rows of a colour (ascending), ``other`` (per
# row of a colour, 6 slots) the index of each slot's neighbour among the other colour's rows (0 for an unused slot:
# coef 0 there).


@wp.kernel
def rb_gather_kernel(
    rows: wp.array(dtype=wp.int32),
    diag: wp.array(dtype=wp.float64),
    values: wp.array(dtype=wp.float64),
    # outputs
    inverse_diag: wp.array(dtype=wp.float64),
    colour_values: wp.array(dtype=wp.float64),
):
    """Per row k of a colour: inverse_diag[k] = 1 / diag[rows[k]], colour_values[k] = values[rows[k]] (the guess
    of the black rows, the right-hand side of the red)."""
    k = wp.tid()
    row = rows[k]
    inverse_diag[k] = wp.float64(1.0) / diag[row]
    colour_values[k] = values[row]


@wp.kernel
def rb_scatter_kernel(
    rows: wp.array(dtype=wp.int32),
    colour_values: wp.array(dtype=wp.float64),
    # outputs
    values: wp.array(dtype=wp.float64),
):
    """values[rows[k]] = colour_values[k] (a colour's solution back into the compact system)."""
    k = wp.tid()
    values[rows[k]] = colour_values[k]


@wp.kernel
def rb_red_kernel(
    A: Stencil,
    red_rows: wp.array(dtype=wp.int32),
    red_other: wp.array2d(dtype=wp.int32),
    red_inverse_diag: wp.array(dtype=wp.float64),
    red_rhs: wp.array(dtype=wp.float64),
    rhs_weight: wp.float64,
    black: wp.array(dtype=wp.float64),
    # outputs
    t: wp.array(dtype=wp.float64),
):
    """t = D_r^-1 (w b_r + N_rb black) per red row (w = ``rhs_weight``: 1 for x_r from x_b, 0 for the first half
    of S p)."""
    k = wp.tid()
    row = red_rows[k]
    acc = rhs_weight * red_rhs[k]
    for m in range(6):
        acc = acc + A.coef[row, m] * black[red_other[k, m]]
    t[k] = acc * red_inverse_diag[k]


@wp.func
def rb_black_row(A: Stencil, black_rows: wp.array(dtype=wp.int32), black_other: wp.array2d(dtype=wp.int32),
                 x: wp.array(dtype=wp.float64), t: wp.array(dtype=wp.float64), k: int):
    """D_b x - N_br t at black row k (``stencil_row``'s order, the red values from ``t``)."""
    row = black_rows[k]
    ax = A.diag[row] * x[k]
    for m in range(6):
        ax = ax - A.coef[row, m] * t[black_other[k, m]]
    return ax


@wp.kernel
def rb_black_matvec_dot_kernel(
    A: Stencil,
    black_rows: wp.array(dtype=wp.int32),
    black_other: wp.array2d(dtype=wp.int32),
    p: wp.array(dtype=wp.float64),
    t: wp.array(dtype=wp.float64),
    chunk: int,
    # outputs
    ap: wp.array(dtype=wp.float64),
    scalars: wp.array(dtype=wp.float64),
):
    """ap = S p = D_b p - N_br t (t = D_r^-1 N_rb p, ``rb_red_kernel``) and scalars[1] += p . ap over the chunk
    [tid * chunk, ...) of the black rows (``pcg_matvec_dot_kernel``'s chunks and partial sums)."""
    tid = wp.tid()
    first = tid * chunk
    last = wp.min(first + chunk, p.shape[0])
    acc0 = wp.float64(0.0)
    acc1 = wp.float64(0.0)
    acc2 = wp.float64(0.0)
    acc3 = wp.float64(0.0)
    quads = first + (last - first) // 4 * 4
    for i in range(first, quads, 4):
        v0 = rb_black_row(A, black_rows, black_other, p, t, i)
        v1 = rb_black_row(A, black_rows, black_other, p, t, i + 1)
        v2 = rb_black_row(A, black_rows, black_other, p, t, i + 2)
        v3 = rb_black_row(A, black_rows, black_other, p, t, i + 3)
        ap[i] = v0
        ap[i + 1] = v1
        ap[i + 2] = v2
        ap[i + 3] = v3
        acc0 = acc0 + p[i] * v0
        acc1 = acc1 + p[i + 1] * v1
        acc2 = acc2 + p[i + 2] * v2
        acc3 = acc3 + p[i + 3] * v3
    for i in range(quads, last):
        v = rb_black_row(A, black_rows, black_other, p, t, i)
        ap[i] = v
        acc0 = acc0 + p[i] * v
    wp.atomic_add(scalars, 1, (acc0 + acc1) + (acc2 + acc3))


@wp.kernel
def rb_black_residual_kernel(
    A: Stencil,
    black_rows: wp.array(dtype=wp.int32),
    black_other: wp.array2d(dtype=wp.int32),
    rhs: wp.array(dtype=wp.float64),
    x: wp.array(dtype=wp.float64),
    t: wp.array(dtype=wp.float64),
    chunk: int,
    # outputs
    r: wp.array(dtype=wp.float64),
    scalars: wp.array(dtype=wp.float64),
):
    """r = b_b - (D_b x - N_br t) with t = x_r = D_r^-1 (b_r + N_rb x) (``rb_red_kernel``, weight 1): the reduced
    residual b_S - S x, which is the full system's residual on the black rows (0 on the red); scalars[3] += r . r
    over the chunk [tid * chunk, ...) of the black rows (four partial sums)."""
    tid = wp.tid()
    first = tid * chunk
    last = wp.min(first + chunk, x.shape[0])
    acc0 = wp.float64(0.0)
    acc1 = wp.float64(0.0)
    acc2 = wp.float64(0.0)
    acc3 = wp.float64(0.0)
    quads = first + (last - first) // 4 * 4
    for i in range(first, quads, 4):
        r0 = rhs[black_rows[i]] - rb_black_row(A, black_rows, black_other, x, t, i)
        r1 = rhs[black_rows[i + 1]] - rb_black_row(A, black_rows, black_other, x, t, i + 1)
        r2 = rhs[black_rows[i + 2]] - rb_black_row(A, black_rows, black_other, x, t, i + 2)
        r3 = rhs[black_rows[i + 3]] - rb_black_row(A, black_rows, black_other, x, t, i + 3)
        r[i] = r0
        r[i + 1] = r1
        r[i + 2] = r2
        r[i + 3] = r3
        acc0 = acc0 + r0 * r0
        acc1 = acc1 + r1 * r1
        acc2 = acc2 + r2 * r2
        acc3 = acc3 + r3 * r3
    for i in range(quads, last):
        ri = rhs[black_rows[i]] - rb_black_row(A, black_rows, black_other, x, t, i)
        r[i] = ri
        acc0 = acc0 + ri * ri
    wp.atomic_add(scalars, 3, (acc0 + acc1) + (acc2 + acc3))


@wp.kernel
def pcg_direction_kernel(
    z: wp.array(dtype=wp.float64),
    scalars: wp.array(dtype=wp.float64),
    # outputs
    p: wp.array(dtype=wp.float64),
):
    """p = z + beta p with beta = scalars[5] (``pcg_ratio_kernel``)."""
    i = wp.tid()
    p[i] = z[i] + scalars[5] * p[i]


@wp.kernel
def pcg_ratio_kernel(
    numerator: int,
    denominator: int,
    slot: int,
    # outputs
    scalars: wp.array(dtype=wp.float64),
    coefficients: wp.array(dtype=wp.float64),
):
    """scalars[slot] = scalars[numerator] / scalars[denominator] (0 if the denominator is 0), one thread: alpha =
    (r.z)/(p.Ap) into slot 4, beta = (r.z)_new/(r.z)_old into slot 5; the same value into coefficients[slot], the
    copy that ``jacobi_step_dot_kernel`` reads (it adds to ``scalars``)."""
    ratio = wp.float64(0.0)
    if scalars[denominator] != wp.float64(0.0):
        ratio = scalars[numerator] / scalars[denominator]
    scalars[slot] = ratio
    coefficients[slot] = ratio


@wp.kernel
def pcg_params_kernel(
    tol: wp.float64,
    atol_floor: wp.float64,
    maxiter: wp.float64,
    # outputs
    params: wp.array(dtype=wp.float64),
):
    """params = (tol, atol_floor, maxiter), one thread: the device-side CG loop's stop test, written before each
    solve outside its captured graph (a launch: no host-to-device copy and no sync)."""
    params[0] = tol
    params[1] = atol_floor
    params[2] = maxiter


@wp.kernel
def pcg_params_floor_kernel(
    tol: wp.float64,
    scale: wp.float64,
    sums: wp.array(dtype=wp.float64),
    index: int,
    maxiter: wp.float64,
    # outputs
    params: wp.array(dtype=wp.float64),
):
    """``pcg_params_kernel`` with atol_floor = scale sqrt(sums[index]) taken on the device: the pressure solve's
    float32 floor from the right-hand side's gross flux (``GasSolver.project``) without reading it back. The host
    takes ``scale * sqrt(x)`` in float64 too: the same bits."""
    params[0] = tol
    params[1] = wp.sqrt(sums[index]) * scale
    params[2] = maxiter


@wp.kernel
def pcg_log_kernel(
    stop: wp.array(dtype=wp.float64),
    slot: int,
    # outputs
    log: wp.array2d(dtype=wp.float64),
):
    """After a device-side CG solve, one thread (``GasSolver`` with deferred checks): log[slot] = (iterations,
    ||r||, bound) of this solve, [3] += 1 when it failed (||r|| not within the bound: not converged, or NaN), and
    [4:7] the first failure's (iterations, ||r||, bound) until ``GasSolver.check`` reads the log and fills it with
    -1 (column 3 <= 0: no failure yet)."""
    atol = stop[0]
    residual = stop[1]
    iterations = stop[2]
    log[slot, 0] = iterations
    log[slot, 1] = residual
    log[slot, 2] = atol
    if not (residual <= atol):
        failed = wp.max(log[slot, 3], wp.float64(0.0))
        if failed == wp.float64(0.0):
            log[slot, 4] = iterations
            log[slot, 5] = residual
            log[slot, 6] = atol
        log[slot, 3] = failed + wp.float64(1.0)


@wp.kernel
def pcg_stop_start_kernel(
    scalars: wp.array(dtype=wp.float64),
    params: wp.array(dtype=wp.float64),
    # outputs
    stop: wp.array(dtype=wp.float64),
    more: wp.array(dtype=wp.int32),
):
    """The device-side loop's start (``GasSolver._device_loop_pcg``), one thread. ``params``: tol, atol_floor,
    maxiter (written before each solve, so one captured graph serves every step). From b.b (scalars[1]) and r.r
    (scalars[3]): the bound atol = max(tol ||b||, atol_floor) into stop[0] (Python's ``max``: a NaN first argument
    stays), ||r|| into stop[1], 0 iterations into stop[2], and ``more`` = 1 unless ||r|| <= atol or maxiter = 0
    (so a NaN residual takes one iteration, as the host loop does): the host loop's numbers, NaN included."""
    first = params[0] * wp.sqrt(scalars[1])
    atol = wp.where(params[1] > first, params[1], first)
    residual = wp.sqrt(scalars[3])
    stop[0] = atol
    stop[1] = residual
    stop[2] = wp.float64(0.0)
    more[0] = wp.where(residual <= atol or params[2] < wp.float64(1.0), 0, 1)


@wp.kernel
def pcg_stop_kernel(
    scalars: wp.array(dtype=wp.float64),
    params: wp.array(dtype=wp.float64),
    # outputs
    stop: wp.array(dtype=wp.float64),
    more: wp.array(dtype=wp.int32),
):
    """After an iteration, one thread: one more iteration in stop[2], ||r|| (scalars[3] = r.r) into stop[1], and
    ``more`` = 1 while ||r|| > stop[0] (NaN stops) and fewer than maxiter (params[2]) iterations were taken."""
    k = stop[2] + wp.float64(1.0)
    residual = wp.sqrt(scalars[3])
    stop[2] = k
    stop[1] = residual
    more[0] = wp.where(residual > stop[0] and k < params[2], 1, 0)


@wp.kernel
def pcg_shift_kernel(
    # outputs
    scalars: wp.array(dtype=wp.float64),
):
    """Next iteration: (r.z)_old = (r.z)_new; clear the accumulators."""
    scalars[0] = scalars[2]
    scalars[1] = wp.float64(0.0)
    scalars[2] = wp.float64(0.0)
    scalars[3] = wp.float64(0.0)
