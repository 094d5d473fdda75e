"""The gas step's hot loops as native C++ (``wp.func_native``) for the CPU device: the same arithmetic as their Warp
counterparts in ``kernels/gas.py``, in the same order, so the same bits (tests/test_gas.py: every loop against its
Warp kernel, and whole steps with and without them, bit for bit).

Why: a Warp CPU kernel addresses every array element through ``wp::address``, which wraps negative indices and
multiplies runtime strides on each access (2-d arrays, arrays inside a struct), and the many array descriptors
spill registers: a 7-point stencil row cost ~7-12 ns that way on this machine's cores. The same loop over raw
pointers costs ~3-5 ns (the rig's viscous matrix, 34,416 rows: 7.1 -> 3.1 ns per row at best, 12.1 -> 4.9 median).
Every multiplication and addition is a statement of its own, as Warp emits them, so the compiler contracts nothing
that Warp's code does not (no ``vfmadd`` in either object code).

What is here, rig timings (best of 60-300 launches, Warp -> native):

- the linear solvers: the native PCG's passes, IC(0) (factor, substitutions: the previous row, the -z neighbour,
  read from a register, 9.1 -> 4.8 ns per row for the step and both substitutions) and the V-cycle's passes
  (``mg_smooth_schedule_kernel``: a level's Gauss-Seidel half-sweeps in one launch);
- the semi-Lagrangian advection (``ADVECT_KERNELS``, 8.0 -> 6.1 ms for the three axes as a loop over faces; then
  in batches of ``BATCH_LANES`` faces taken stage by stage, SIMD across the batch, ~1.8x less again, same bits);
- the cell and face passes: pressure right-hand side and matrix (4.7 -> 2.7 ms), the projection's cell pass
  (2.3 -> 1.4), Smagorinsky (2.1 -> 1.7: nine divisions and a square root per cell; then ~1.5x less again with
  the divisions and the root SIMD over batches of ``BATCH_LANES`` cells), the viscous assembly with the
  forces (``VISCOUS_RHS_KERNELS``, 4.5 -> 2.8 for three axes), face coefficients, pressure correction, cell state,
  viscous store and pressure increment.

Each kernel has the signature of the ``kernels/gas.py`` kernel of the same name, so a launch takes either
(``for_device`` picks, at the bottom). The solver loops run in one thread (``dim=1``: the CPU runs a launch's
threads one after another in order, so one thread over all rows is the same order), except the chunked
dot-product passes, which keep ``chunk`` rows per thread (``kernels/gas.py`` DOT_CHUNK on the CPU) and one atomic add per chunk (the same partial sums);
the cell and face passes keep their kernels' ``block`` entries per thread. The native loops need contiguous
arrays (``for_device`` checks when a launch is recorded). Only the CPU launches them: the CUDA path keeps the Warp
kernels (the module still compiles for CUDA, as ``wp.force_load`` on a GPU builds every module: tested with
NVRTC).
"""

import warp as wp

from kernels import gas as K

f64 = wp.float64

# a stencil row (A x)_i = diag_i x_i - sum_m coef_im x_nb(i,m), ``kernels/gas.py`` ``stencil_row``'s order
_ROW = """
    auto stencil_row = [&](const double* __restrict__ xv, int i) {
        double ax = d[i] * xv[i];
        const double* ci = c + 6 * (size_t)i;
        const int* ni = nb + 6 * (size_t)i;
        for (int m = 0; m < 6; ++m) {
            double t = ci[m] * xv[ni[m]];
            ax = ax - t;
        }
        return ax;
    };
"""

_STENCIL = """
    const double* __restrict__ d = diag.data;
    const double* __restrict__ c = coef.data;
    const int* __restrict__ nb = neighbour.data;
"""


@wp.func_native(_STENCIL + _ROW + """
    const double* __restrict__ x = p.data;
    double* __restrict__ y = ap.data;
    double acc0 = 0.0, acc1 = 0.0, acc2 = 0.0, acc3 = 0.0;
    int quads = first + (last - first) / 4 * 4;
    for (int i = first; i < quads; i += 4) {
        double v0 = stencil_row(x, i);
        double v1 = stencil_row(x, i + 1);
        double v2 = stencil_row(x, i + 2);
        double v3 = stencil_row(x, i + 3);
        y[i] = v0;
        y[i + 1] = v1;
        y[i + 2] = v2;
        y[i + 3] = v3;
        double t0 = x[i] * v0;
        double t1 = x[i + 1] * v1;
        double t2 = x[i + 2] * v2;
        double t3 = x[i + 3] * v3;
        acc0 = acc0 + t0;
        acc1 = acc1 + t1;
        acc2 = acc2 + t2;
        acc3 = acc3 + t3;
    }
    for (int i = quads; i < last; ++i) {
        double v = stencil_row(x, i);
        y[i] = v;
        double t = x[i] * v;
        acc0 = acc0 + t;
    }
    double s01 = acc0 + acc1;
    double s23 = acc2 + acc3;
    return s01 + s23;
""")
def matvec_dot_chunk(diag: wp.array(dtype=f64), coef: wp.array2d(dtype=f64), neighbour: wp.array2d(dtype=wp.int32),
                     p: wp.array(dtype=f64), ap: wp.array(dtype=f64), first: int, last: int) -> f64:
    """ap = A p over rows [first, last) and the chunk's p . ap (``pcg_matvec_dot_kernel``)."""
    ...


@wp.kernel
def pcg_matvec_dot_kernel(
    A: K.Stencil,
    p: wp.array(dtype=f64),
    slot: int,
    chunk: int,
    # outputs
    ap: wp.array(dtype=f64),
    scalars: wp.array(dtype=f64),
):
    """``kernels/gas.py`` ``pcg_matvec_dot_kernel`` (one ``chunk`` of rows per thread)."""
    t = wp.tid()
    first = t * chunk
    last = wp.min(first + chunk, p.shape[0])
    wp.atomic_add(scalars, slot, matvec_dot_chunk(A.diag, A.coef, A.neighbour, p, ap, first, last))


@wp.func_native(_STENCIL + _ROW + """
    const double* __restrict__ xv = x.data;
    const double* __restrict__ b = rhs.data;
    double* __restrict__ rv = r.data;
    double bb0 = 0.0, bb1 = 0.0, bb2 = 0.0, bb3 = 0.0;
    double rr0 = 0.0, rr1 = 0.0, rr2 = 0.0, rr3 = 0.0;
    int quads = first + (last - first) / 4 * 4;
    for (int i = first; i < quads; i += 4) {
        double r0 = b[i] - stencil_row(xv, i);
        double r1 = b[i + 1] - stencil_row(xv, i + 1);
        double r2 = b[i + 2] - stencil_row(xv, i + 2);
        double r3 = b[i + 3] - stencil_row(xv, i + 3);
        rv[i] = r0;
        rv[i + 1] = r1;
        rv[i + 2] = r2;
        rv[i + 3] = r3;
        double q0 = b[i] * b[i];
        double q1 = b[i + 1] * b[i + 1];
        double q2 = b[i + 2] * b[i + 2];
        double q3 = b[i + 3] * b[i + 3];
        bb0 = bb0 + q0;
        bb1 = bb1 + q1;
        bb2 = bb2 + q2;
        bb3 = bb3 + q3;
        double s0 = r0 * r0;
        double s1 = r1 * r1;
        double s2 = r2 * r2;
        double s3 = r3 * r3;
        rr0 = rr0 + s0;
        rr1 = rr1 + s1;
        rr2 = rr2 + s2;
        rr3 = rr3 + s3;
    }
    for (int i = quads; i < last; ++i) {
        double ri = b[i] - stencil_row(xv, i);
        rv[i] = ri;
        double q = b[i] * b[i];
        bb0 = bb0 + q;
        double s = ri * ri;
        rr0 = rr0 + s;
    }
    double b01 = bb0 + bb1;
    double b23 = bb2 + bb3;
    double r01 = rr0 + rr1;
    double r23 = rr2 + rr3;
    return wp::vec_t<2, double>(b01 + b23, r01 + r23);
""")
def residual_start_chunk(diag: wp.array(dtype=f64), coef: wp.array2d(dtype=f64),
                         neighbour: wp.array2d(dtype=wp.int32), x: wp.array(dtype=f64), rhs: wp.array(dtype=f64),
                         r: wp.array(dtype=f64), first: int, last: int) -> wp.vec2d:
    """r = b - A x over rows [first, last); the chunk's (b . b, r . r) (``pcg_residual_start_kernel``)."""
    ...


@wp.kernel
def pcg_residual_start_kernel(
    A: K.Stencil,
    x: wp.array(dtype=f64),
    rhs: wp.array(dtype=f64),
    chunk: int,
    # outputs
    r: wp.array(dtype=f64),
    scalars: wp.array(dtype=f64),
):
    """``kernels/gas.py`` ``pcg_residual_start_kernel`` (one ``chunk`` of rows per thread)."""
    t = wp.tid()
    first = t * chunk
    last = wp.min(first + chunk, x.shape[0])
    sums = residual_start_chunk(A.diag, A.coef, A.neighbour, x, rhs, r, first, last)
    wp.atomic_add(scalars, 1, sums[0])
    wp.atomic_add(scalars, 3, sums[1])


@wp.func_native("""
    const double* __restrict__ pv = p.data;
    const double* __restrict__ apv = ap.data;
    double* __restrict__ xv = x.data;
    double* __restrict__ rv = r.data;
    double alpha = scalars.data[4];
    int n = p.shape[0];
    for (int i = 0; i < n; ++i) {
        double t = alpha * pv[i];
        xv[i] = xv[i] + t;
        double u = alpha * apv[i];
        rv[i] = rv[i] - u;
    }
""")
def step_rows(p: wp.array(dtype=f64), ap: wp.array(dtype=f64), scalars: wp.array(dtype=f64),
              x: wp.array(dtype=f64), r: wp.array(dtype=f64)):
    ...


@wp.kernel
def pcg_step_kernel(
    p: wp.array(dtype=f64),
    ap: wp.array(dtype=f64),
    scalars: wp.array(dtype=f64),
    # outputs
    x: wp.array(dtype=f64),
    r: wp.array(dtype=f64),
):
    """``kernels/gas.py`` ``pcg_step_kernel`` over every row (launch one thread)."""
    step_rows(p, ap, scalars, x, r)


@wp.func_native("""
    const double* __restrict__ zv = z.data;
    double* __restrict__ pv = p.data;
    double beta = scalars.data[5];
    int n = p.shape[0];
    for (int i = 0; i < n; ++i) {
        double t = beta * pv[i];
        pv[i] = zv[i] + t;
    }
""")
def direction_rows(z: wp.array(dtype=f64), scalars: wp.array(dtype=f64), p: wp.array(dtype=f64)):
    ...


@wp.kernel
def pcg_direction_kernel(
    z: wp.array(dtype=f64),
    scalars: wp.array(dtype=f64),
    # outputs
    p: wp.array(dtype=f64),
):
    """``kernels/gas.py`` ``pcg_direction_kernel`` over every row (launch one thread)."""
    direction_rows(z, scalars, p)


@wp.func_native("""
    const double* __restrict__ av = a.data;
    const double* __restrict__ bv = b.data;
    double ab0 = 0.0, ab1 = 0.0, ab2 = 0.0, ab3 = 0.0;
    double aa0 = 0.0, aa1 = 0.0, aa2 = 0.0, aa3 = 0.0;
    int quads = first + (last - first) / 4 * 4;
    for (int i = first; i < quads; i += 4) {
        double t0 = av[i] * bv[i];
        double t1 = av[i + 1] * bv[i + 1];
        double t2 = av[i + 2] * bv[i + 2];
        double t3 = av[i + 3] * bv[i + 3];
        ab0 = ab0 + t0;
        ab1 = ab1 + t1;
        ab2 = ab2 + t2;
        ab3 = ab3 + t3;
        double s0 = av[i] * av[i];
        double s1 = av[i + 1] * av[i + 1];
        double s2 = av[i + 2] * av[i + 2];
        double s3 = av[i + 3] * av[i + 3];
        aa0 = aa0 + s0;
        aa1 = aa1 + s1;
        aa2 = aa2 + s2;
        aa3 = aa3 + s3;
    }
    for (int i = quads; i < last; ++i) {
        double t = av[i] * bv[i];
        ab0 = ab0 + t;
        double s = av[i] * av[i];
        aa0 = aa0 + s;
    }
    double x01 = ab0 + ab1;
    double x23 = ab2 + ab3;
    double y01 = aa0 + aa1;
    double y23 = aa2 + aa3;
    return wp::vec_t<2, double>(x01 + x23, y01 + y23);
""")
def dot_pair_chunk(a: wp.array(dtype=f64), b: wp.array(dtype=f64), first: int, last: int) -> wp.vec2d:
    ...


@wp.kernel
def pcg_dot_pair_kernel(
    a: wp.array(dtype=f64),
    b: wp.array(dtype=f64),
    slot_ab: int,
    slot_aa: int,
    chunk: int,
    # outputs
    scalars: wp.array(dtype=f64),
):
    """``kernels/gas.py`` ``pcg_dot_pair_kernel`` (one ``chunk`` of rows per thread)."""
    t = wp.tid()
    first = t * chunk
    last = wp.min(first + chunk, a.shape[0])
    sums = dot_pair_chunk(a, b, first, last)
    wp.atomic_add(scalars, slot_ab, sums[0])
    wp.atomic_add(scalars, slot_aa, sums[1])


# ----------------------------------------------------------------- Jacobi preconditioner


@wp.func_native("""
    const double* __restrict__ dv = diag.data;
    const double* __restrict__ rv = r.data;
    double* __restrict__ inv = inverse_diag.data;
    double* __restrict__ zv = z.data;
    int n = r.shape[0];
    for (int i = 0; i < n; ++i) {
        double inverse = 1.0 / dv[i];
        inv[i] = inverse;
        zv[i] = rv[i] * inverse;
    }
""")
def jacobi_start_rows(diag: wp.array(dtype=f64), r: wp.array(dtype=f64), inverse_diag: wp.array(dtype=f64),
                      z: wp.array(dtype=f64)):
    ...


@wp.kernel
def jacobi_start_kernel(
    diag: wp.array(dtype=f64),
    r: wp.array(dtype=f64),
    # outputs
    inverse_diag: wp.array(dtype=f64),
    z: wp.array(dtype=f64),
):
    """``kernels/gas.py`` ``jacobi_start_kernel`` over every row (launch one thread)."""
    jacobi_start_rows(diag, r, inverse_diag, z)


@wp.func_native("""
    const double* __restrict__ inv = inverse_diag.data;
    const double* __restrict__ pv = p.data;
    const double* __restrict__ apv = ap.data;
    double* __restrict__ xv = x.data;
    double* __restrict__ rv = r.data;
    double* __restrict__ zv = z.data;
    double alpha = scalars.data[4];
    double rz0 = 0.0, rz1 = 0.0, rz2 = 0.0, rz3 = 0.0;
    double rr0 = 0.0, rr1 = 0.0, rr2 = 0.0, rr3 = 0.0;
    int quads = first + (last - first) / 4 * 4;
    for (int i = first; i < quads; i += 4) {
        double a0 = alpha * pv[i];
        double a1 = alpha * pv[i + 1];
        double a2 = alpha * pv[i + 2];
        double a3 = alpha * pv[i + 3];
        xv[i] = xv[i] + a0;
        xv[i + 1] = xv[i + 1] + a1;
        xv[i + 2] = xv[i + 2] + a2;
        xv[i + 3] = xv[i + 3] + a3;
        double b0 = alpha * apv[i];
        double b1 = alpha * apv[i + 1];
        double b2 = alpha * apv[i + 2];
        double b3 = alpha * apv[i + 3];
        double r0 = rv[i] - b0;
        double r1 = rv[i + 1] - b1;
        double r2 = rv[i + 2] - b2;
        double r3 = rv[i + 3] - b3;
        rv[i] = r0;
        rv[i + 1] = r1;
        rv[i + 2] = r2;
        rv[i + 3] = r3;
        double z0 = r0 * inv[i];
        double z1 = r1 * inv[i + 1];
        double z2 = r2 * inv[i + 2];
        double z3 = r3 * inv[i + 3];
        zv[i] = z0;
        zv[i + 1] = z1;
        zv[i + 2] = z2;
        zv[i + 3] = z3;
        double t0 = r0 * z0;
        double t1 = r1 * z1;
        double t2 = r2 * z2;
        double t3 = r3 * z3;
        rz0 = rz0 + t0;
        rz1 = rz1 + t1;
        rz2 = rz2 + t2;
        rz3 = rz3 + t3;
        double s0 = r0 * r0;
        double s1 = r1 * r1;
        double s2 = r2 * r2;
        double s3 = r3 * r3;
        rr0 = rr0 + s0;
        rr1 = rr1 + s1;
        rr2 = rr2 + s2;
        rr3 = rr3 + s3;
    }
    for (int i = quads; i < last; ++i) {
        double a = alpha * pv[i];
        xv[i] = xv[i] + a;
        double b = alpha * apv[i];
        double ri = rv[i] - b;
        rv[i] = ri;
        double zi = ri * inv[i];
        zv[i] = zi;
        double t = ri * zi;
        rz0 = rz0 + t;
        double s = ri * ri;
        rr0 = rr0 + s;
    }
    double x01 = rz0 + rz1;
    double x23 = rz2 + rz3;
    double y01 = rr0 + rr1;
    double y23 = rr2 + rr3;
    return wp::vec_t<2, double>(x01 + x23, y01 + y23);
""")
def jacobi_step_dot_chunk(inverse_diag: wp.array(dtype=f64), p: wp.array(dtype=f64), ap: wp.array(dtype=f64),
                          scalars: wp.array(dtype=f64), x: wp.array(dtype=f64), r: wp.array(dtype=f64),
                          z: wp.array(dtype=f64), first: int, last: int) -> wp.vec2d:
    """The step, z = D^-1 r over rows [first, last) and the chunk's (r . z, r . r) (``jacobi_step_dot_kernel``)."""
    ...


@wp.kernel
def jacobi_step_dot_kernel(
    inverse_diag: wp.array(dtype=f64),
    p: wp.array(dtype=f64),
    ap: wp.array(dtype=f64),
    coefficients: wp.array(dtype=f64),
    chunk: int,
    # outputs
    x: wp.array(dtype=f64),
    r: wp.array(dtype=f64),
    z: wp.array(dtype=f64),
    scalars: wp.array(dtype=f64),
):
    """``kernels/gas.py`` ``jacobi_step_dot_kernel`` (one ``chunk`` of rows per thread; alpha from ``coefficients``)."""
    t = wp.tid()
    first = t * chunk
    last = wp.min(first + chunk, p.shape[0])
    sums = jacobi_step_dot_chunk(inverse_diag, p, ap, coefficients, x, r, z, first, last)
    wp.atomic_add(scalars, 2, sums[0])
    wp.atomic_add(scalars, 3, sums[1])


# ----------------------------------------------------------------- red-black reduced system (kernels/gas.py ``rb_*``)


@wp.func_native("""
    const int* __restrict__ rw = rows.data;
    const double* __restrict__ dv = diag.data;
    const double* __restrict__ vv = values.data;
    double* __restrict__ inv = inverse_diag.data;
    double* __restrict__ cv = colour_values.data;
    int n = rows.shape[0];
    for (int k = 0; k < n; ++k) {
        int row = rw[k];
        inv[k] = 1.0 / dv[row];
        cv[k] = vv[row];
    }
""")
def rb_gather_rows(rows: wp.array(dtype=wp.int32), diag: wp.array(dtype=f64), values: wp.array(dtype=f64),
                   inverse_diag: wp.array(dtype=f64), colour_values: wp.array(dtype=f64)):
    ...


@wp.kernel
def rb_gather_kernel(
    rows: wp.array(dtype=wp.int32),
    diag: wp.array(dtype=f64),
    values: wp.array(dtype=f64),
    # outputs
    inverse_diag: wp.array(dtype=f64),
    colour_values: wp.array(dtype=f64),
):
    """``kernels/gas.py`` ``rb_gather_kernel`` over every row of the colour (launch one thread)."""
    rb_gather_rows(rows, diag, values, inverse_diag, colour_values)


@wp.func_native("""
    const int* __restrict__ rw = rows.data;
    const double* __restrict__ cv = colour_values.data;
    double* __restrict__ vv = values.data;
    int n = rows.shape[0];
    for (int k = 0; k < n; ++k)
        vv[rw[k]] = cv[k];
""")
def rb_scatter_rows(rows: wp.array(dtype=wp.int32), colour_values: wp.array(dtype=f64), values: wp.array(dtype=f64)):
    ...


@wp.kernel
def rb_scatter_kernel(
    rows: wp.array(dtype=wp.int32),
    colour_values: wp.array(dtype=f64),
    # outputs
    values: wp.array(dtype=f64),
):
    """``kernels/gas.py`` ``rb_scatter_kernel`` over every row of the colour (launch one thread)."""
    rb_scatter_rows(rows, colour_values, values)


@wp.func_native("""
    const double* __restrict__ c = coef.data;
    const int* __restrict__ rw = red_rows.data;
    const int* __restrict__ other = red_other.data;
    const double* __restrict__ inv = red_inverse_diag.data;
    const double* __restrict__ br = red_rhs.data;
    const double* __restrict__ bv = black.data;
    double* __restrict__ tv = t.data;
    int n = red_rows.shape[0];
    for (int k = 0; k < n; ++k) {
        const double* ck = c + 6 * (size_t)rw[k];
        const int* ok = other + 6 * (size_t)k;
        double acc = rhs_weight * br[k];
        for (int m = 0; m < 6; ++m) {
            double u = ck[m] * bv[ok[m]];
            acc = acc + u;
        }
        tv[k] = acc * inv[k];
    }
""")
def rb_red_rows(coef: wp.array2d(dtype=f64), red_rows: wp.array(dtype=wp.int32), red_other: wp.array2d(dtype=wp.int32),
                red_inverse_diag: wp.array(dtype=f64), red_rhs: wp.array(dtype=f64), rhs_weight: f64,
                black: wp.array(dtype=f64), t: wp.array(dtype=f64)):
    ...


@wp.kernel
def rb_red_kernel(
    A: K.Stencil,
    red_rows: wp.array(dtype=wp.int32),
    red_other: wp.array2d(dtype=wp.int32),
    red_inverse_diag: wp.array(dtype=f64),
    red_rhs: wp.array(dtype=f64),
    rhs_weight: f64,
    black: wp.array(dtype=f64),
    # outputs
    t: wp.array(dtype=f64),
):
    """``kernels/gas.py`` ``rb_red_kernel`` over every red row (launch one thread)."""
    rb_red_rows(A.coef, red_rows, red_other, red_inverse_diag, red_rhs, rhs_weight, black, t)


# D_b x - N_br t at black row k (``rb_black_row``'s order)
_BLACK_ROW = """
    const double* __restrict__ d = diag.data;
    const double* __restrict__ c = coef.data;
    const int* __restrict__ rw = black_rows.data;
    const int* __restrict__ other = black_other.data;
    const double* __restrict__ tv = t.data;
    auto black_row = [&](const double* __restrict__ xv, int k) {
        int row = rw[k];
        double ax = d[row] * xv[k];
        const double* ck = c + 6 * (size_t)row;
        const int* ok = other + 6 * (size_t)k;
        for (int m = 0; m < 6; ++m) {
            double u = ck[m] * tv[ok[m]];
            ax = ax - u;
        }
        return ax;
    };
"""


@wp.func_native(_BLACK_ROW + """
    const double* __restrict__ pv = p.data;
    double* __restrict__ y = ap.data;
    double acc0 = 0.0, acc1 = 0.0, acc2 = 0.0, acc3 = 0.0;
    int quads = first + (last - first) / 4 * 4;
    for (int i = first; i < quads; i += 4) {
        double v0 = black_row(pv, i);
        double v1 = black_row(pv, i + 1);
        double v2 = black_row(pv, i + 2);
        double v3 = black_row(pv, i + 3);
        y[i] = v0;
        y[i + 1] = v1;
        y[i + 2] = v2;
        y[i + 3] = v3;
        double t0 = pv[i] * v0;
        double t1 = pv[i + 1] * v1;
        double t2 = pv[i + 2] * v2;
        double t3 = pv[i + 3] * v3;
        acc0 = acc0 + t0;
        acc1 = acc1 + t1;
        acc2 = acc2 + t2;
        acc3 = acc3 + t3;
    }
    for (int i = quads; i < last; ++i) {
        double v = black_row(pv, i);
        y[i] = v;
        double u = pv[i] * v;
        acc0 = acc0 + u;
    }
    double s01 = acc0 + acc1;
    double s23 = acc2 + acc3;
    return s01 + s23;
""")
def rb_black_matvec_dot_chunk(diag: wp.array(dtype=f64), coef: wp.array2d(dtype=f64),
                              black_rows: wp.array(dtype=wp.int32), black_other: wp.array2d(dtype=wp.int32),
                              p: wp.array(dtype=f64), t: wp.array(dtype=f64), ap: wp.array(dtype=f64), first: int,
                              last: int) -> f64:
    """ap = D_b p - N_br t over black rows [first, last) and the chunk's p . ap (``rb_black_matvec_dot_kernel``)."""
    ...


@wp.kernel
def rb_black_matvec_dot_kernel(
    A: K.Stencil,
    black_rows: wp.array(dtype=wp.int32),
    black_other: wp.array2d(dtype=wp.int32),
    p: wp.array(dtype=f64),
    t: wp.array(dtype=f64),
    chunk: int,
    # outputs
    ap: wp.array(dtype=f64),
    scalars: wp.array(dtype=f64),
):
    """``kernels/gas.py`` ``rb_black_matvec_dot_kernel`` (one ``chunk`` of rows per thread)."""
    tid = wp.tid()
    first = tid * chunk
    last = wp.min(first + chunk, p.shape[0])
    wp.atomic_add(scalars, 1, rb_black_matvec_dot_chunk(A.diag, A.coef, black_rows, black_other, p, t, ap, first, last))


@wp.func_native(_BLACK_ROW + """
    const double* __restrict__ b = rhs.data;
    const double* __restrict__ xv = x.data;
    double* __restrict__ rv = r.data;
    double acc0 = 0.0, acc1 = 0.0, acc2 = 0.0, acc3 = 0.0;
    int quads = first + (last - first) / 4 * 4;
    for (int i = first; i < quads; i += 4) {
        double r0 = b[rw[i]] - black_row(xv, i);
        double r1 = b[rw[i + 1]] - black_row(xv, i + 1);
        double r2 = b[rw[i + 2]] - black_row(xv, i + 2);
        double r3 = b[rw[i + 3]] - black_row(xv, i + 3);
        rv[i] = r0;
        rv[i + 1] = r1;
        rv[i + 2] = r2;
        rv[i + 3] = r3;
        double s0 = r0 * r0;
        double s1 = r1 * r1;
        double s2 = r2 * r2;
        double s3 = r3 * r3;
        acc0 = acc0 + s0;
        acc1 = acc1 + s1;
        acc2 = acc2 + s2;
        acc3 = acc3 + s3;
    }
    for (int i = quads; i < last; ++i) {
        double ri = b[rw[i]] - black_row(xv, i);
        rv[i] = ri;
        double s = ri * ri;
        acc0 = acc0 + s;
    }
    double s01 = acc0 + acc1;
    double s23 = acc2 + acc3;
    return s01 + s23;
""")
def rb_black_residual_chunk(diag: wp.array(dtype=f64), coef: wp.array2d(dtype=f64),
                            black_rows: wp.array(dtype=wp.int32), black_other: wp.array2d(dtype=wp.int32),
                            rhs: wp.array(dtype=f64), x: wp.array(dtype=f64), t: wp.array(dtype=f64),
                            r: wp.array(dtype=f64), first: int, last: int) -> f64:
    """r = b_b - (D_b x - N_br t) over black rows [first, last) and the chunk's r . r (``rb_black_residual_kernel``)."""
    ...


@wp.kernel
def rb_black_residual_kernel(
    A: K.Stencil,
    black_rows: wp.array(dtype=wp.int32),
    black_other: wp.array2d(dtype=wp.int32),
    rhs: wp.array(dtype=f64),
    x: wp.array(dtype=f64),
    t: wp.array(dtype=f64),
    chunk: int,
    # outputs
    r: wp.array(dtype=f64),
    scalars: wp.array(dtype=f64),
):
    """``kernels/gas.py`` ``rb_black_residual_kernel`` (one ``chunk`` of rows per thread)."""
    tid = wp.tid()
    first = tid * chunk
    last = wp.min(first + chunk, x.shape[0])
    wp.atomic_add(scalars, 3, rb_black_residual_chunk(A.diag, A.coef, black_rows, black_other, rhs, x, t, r, first,
                                                      last))


# ----------------------------------------------------------------- incomplete Cholesky (one thread, as in kernels/gas.py)


@wp.func_native(_STENCIL + """
    double* __restrict__ pv = pivot.data;
    double* __restrict__ pinv = pivot_inverse.data;
    double floor = 1.0e-3;
    if (relaxation > 0.0)
        floor = 0.25;
    double p_previous = 0.0;  // pivot of row i - 1 in a register (the -z neighbour of a row is the row before)
    for (int i = 0; i < n; ++i) {
        double di = d[i];
        for (int m = 0; m < 6; ++m) {
            int j = nb[6 * (size_t)i + m];
            double cm = c[6 * (size_t)i + m];
            if (j < i && cm != 0.0) {
                double fill = 0.0;
                if (relaxation > 0.0) {
                    for (int m2 = 0; m2 < 6; ++m2) {
                        int k = nb[6 * (size_t)j + m2];
                        if (k > j && k != i)
                            fill = fill + c[6 * (size_t)j + m2];
                    }
                }
                double t1 = relaxation * fill;
                double t2 = cm + t1;
                double t3 = cm * t2;
                double t4 = t3 / (j == i - 1 ? p_previous : pv[j]);
                di = di - t4;
            }
        }
        double bound = floor * d[i];
        if (di <= bound)
            di = d[i];
        p_previous = di;
        pv[i] = di;
        pinv[i] = 1.0 / di;
    }
""")
def ic0_factor_rows(diag: wp.array(dtype=f64), coef: wp.array2d(dtype=f64), neighbour: wp.array2d(dtype=wp.int32),
                    n: int, relaxation: f64, pivot: wp.array(dtype=f64), pivot_inverse: wp.array(dtype=f64)):
    ...


@wp.kernel
def ic0_factor_kernel(
    A: K.Stencil,
    n: int,
    relaxation: f64,
    # outputs
    pivot: wp.array(dtype=f64),
    pivot_inverse: wp.array(dtype=f64),
):
    """``kernels/gas.py`` ``ic0_factor_kernel`` (one thread)."""
    ic0_factor_rows(A.diag, A.coef, A.neighbour, n, relaxation, pivot, pivot_inverse)


# forward then backward substitution of IC(0) into z (``ic0_apply_kernel``'s order); ``rv`` the right-hand side,
# FORWARD_PROLOGUE what a row does before its forward substitution (``ic0_step_apply_kernel``: the step)
_SUBSTITUTIONS = """
    double z_previous = 0.0;  // z of row i - 1, kept in a register: the -z neighbour of a row is the row before
    for (int i = 0; i < n; ++i) {
        FORWARD_PROLOGUE
        double acc = rv[i];
        if (ordered != 0) {
            zv[i] = 0.0;
            for (int m = 0; m < 4; m += 2) {
                double t = c[6 * (size_t)i + m] * zv[nb[6 * (size_t)i + m]];
                acc = acc + t;
            }
            int below = nb[6 * (size_t)i + 4];
            double z_below = below == i - 1 ? z_previous : zv[below];
            double t = c[6 * (size_t)i + 4] * z_below;
            acc = acc + t;
        } else {
            for (int m = 0; m < 6; ++m) {
                int j = nb[6 * (size_t)i + m];
                if (j < i) {
                    double t = c[6 * (size_t)i + m] * (j == i - 1 ? z_previous : zv[j]);
                    acc = acc + t;
                }
            }
        }
        z_previous = acc * pinv[i];
        zv[i] = z_previous;
    }
    double z_next = 0.0;  // z of row i + 1 (its +z neighbour when in the same column), in a register
    for (int step = 0; step < n; ++step) {
        int i = n - 1 - step;
        double acc = 0.0;
        if (ordered != 0) {
            for (int m = 1; m < 4; m += 2) {
                double t = c[6 * (size_t)i + m] * zv[nb[6 * (size_t)i + m]];
                acc = acc + t;
            }
            int above = nb[6 * (size_t)i + 5];
            double z_above = above == i + 1 ? z_next : zv[above];
            double t = c[6 * (size_t)i + 5] * z_above;
            acc = acc + t;
        } else {
            for (int m = 0; m < 6; ++m) {
                int j = nb[6 * (size_t)i + m];
                if (j > i) {
                    double t = c[6 * (size_t)i + m] * (j == i + 1 ? z_next : zv[j]);
                    acc = acc + t;
                }
            }
        }
        double u = acc * pinv[i];
        z_next = zv[i] + u;
        zv[i] = z_next;
    }
"""


@wp.func_native("""
    const double* __restrict__ c = coef.data;
    const int* __restrict__ nb = neighbour.data;
    const double* __restrict__ pinv = pivot_inverse.data;
    const double* __restrict__ rv = r.data;
    double* __restrict__ zv = z.data;
    const int ordered = 0;
""" + _SUBSTITUTIONS.replace("FORWARD_PROLOGUE", ""))
def ic0_apply_rows(pivot_inverse: wp.array(dtype=f64), coef: wp.array2d(dtype=f64),
                   neighbour: wp.array2d(dtype=wp.int32), r: wp.array(dtype=f64), n: int, z: wp.array(dtype=f64)):
    ...


@wp.kernel
def ic0_apply_kernel(
    pivot_inverse: wp.array(dtype=f64),
    A: K.Stencil,
    r: wp.array(dtype=f64),
    n: int,
    # outputs
    z: wp.array(dtype=f64),
):
    """``kernels/gas.py`` ``ic0_apply_kernel`` (one thread)."""
    ic0_apply_rows(pivot_inverse, A.coef, A.neighbour, r, n, z)


@wp.func_native("""
    const double* __restrict__ c = coef.data;
    const int* __restrict__ nb = neighbour.data;
    const double* __restrict__ pinv = pivot_inverse.data;
    const double* __restrict__ pv = p.data;
    const double* __restrict__ apv = ap.data;
    double* __restrict__ xv = x.data;
    double* __restrict__ rv = r.data;
    double* __restrict__ zv = z.data;
    double alpha = scalars.data[4];
""" + _SUBSTITUTIONS.replace("FORWARD_PROLOGUE", """
        double step_x = alpha * pv[i];
        xv[i] = xv[i] + step_x;
        double step_r = alpha * apv[i];
        rv[i] = rv[i] - step_r;"""))
def ic0_step_apply_rows(pivot_inverse: wp.array(dtype=f64), coef: wp.array2d(dtype=f64),
                        neighbour: wp.array2d(dtype=wp.int32), p: wp.array(dtype=f64), ap: wp.array(dtype=f64),
                        scalars: wp.array(dtype=f64), n: int, ordered: int, x: wp.array(dtype=f64),
                        r: wp.array(dtype=f64), z: wp.array(dtype=f64)):
    ...


@wp.kernel
def ic0_step_apply_kernel(
    pivot_inverse: wp.array(dtype=f64),
    A: K.Stencil,
    p: wp.array(dtype=f64),
    ap: wp.array(dtype=f64),
    scalars: wp.array(dtype=f64),
    n: int,
    ordered: int,
    # outputs
    x: wp.array(dtype=f64),
    r: wp.array(dtype=f64),
    z: wp.array(dtype=f64),
):
    """``kernels/gas.py`` ``ic0_step_apply_kernel`` (one thread)."""
    ic0_step_apply_rows(pivot_inverse, A.coef, A.neighbour, p, ap, scalars, n, ordered, x, r, z)


# ----------------------------------------------------------------- multigrid V-cycle (hel_warp/gas/multigrid.py), one thread


@wp.func_native(_STENCIL + """
    const double* __restrict__ invd = inverse_diag.data;
    const int* __restrict__ rw = rows.data;
    const double* __restrict__ bv = b.data;
    double* __restrict__ zv = z.data;
    int count = rows.shape[0];
    for (int idx = 0; idx < count; ++idx) {
        int r = rw[idx];
        double acc = bv[r];
        const double* cr = c + 6 * (size_t)r;
        const int* nr = nb + 6 * (size_t)r;
        for (int m = 0; m < 6; ++m) {
            double t = cr[m] * zv[nr[m]];
            acc = acc + t;
        }
        if (invd[r] > 0.0)
            zv[r] = acc * invd[r];
    }
""")
def smooth_rows(diag: wp.array(dtype=f64), coef: wp.array2d(dtype=f64), neighbour: wp.array2d(dtype=wp.int32),
                inverse_diag: wp.array(dtype=f64), rows: wp.array(dtype=wp.int32), b: wp.array(dtype=f64),
                z: wp.array(dtype=f64)):
    ...


@wp.kernel
def mg_smooth_kernel(
    A: K.Stencil,
    inverse_diag: wp.array(dtype=f64),
    rows: wp.array(dtype=wp.int32),
    b: wp.array(dtype=f64),
    # outputs
    z: wp.array(dtype=f64),
):
    """``kernels/gas.py`` ``mg_smooth_kernel`` over every entry of ``rows`` in order (launch one thread)."""
    smooth_rows(A.diag, A.coef, A.neighbour, inverse_diag, rows, b, z)


@wp.kernel
def mg_smooth_schedule_kernel(
    A: K.Stencil,
    inverse_diag: wp.array(dtype=f64),
    rows0: wp.array(dtype=wp.int32),
    rows1: wp.array(dtype=wp.int32),
    rows2: wp.array(dtype=wp.int32),
    schedule: wp.array(dtype=wp.int32),
    b: wp.array(dtype=f64),
    # outputs
    z: wp.array(dtype=f64),
):
    """The Gauss-Seidel updates of the colours ``schedule`` lists (0, 1, 2: ``rows0``, ``rows1``, ``rows2``), in that
    order, in one launch (one thread): ``mg_smooth_kernel`` once per entry, without a launch each (~4 us on the
    CPU, ~10 half-sweeps per level and V-cycle)."""
    for s in range(schedule.shape[0]):
        colour = schedule[s]
        if colour == 0:
            smooth_rows(A.diag, A.coef, A.neighbour, inverse_diag, rows0, b, z)
        elif colour == 1:
            smooth_rows(A.diag, A.coef, A.neighbour, inverse_diag, rows1, b, z)
        else:
            smooth_rows(A.diag, A.coef, A.neighbour, inverse_diag, rows2, b, z)


@wp.func_native("""
    const double* __restrict__ invd = inverse_diag.data;
    const int* __restrict__ col = colour.data;
    const double* __restrict__ bv = b.data;
    double* __restrict__ zv = z.data;
    int n = z.shape[0];
    for (int r = 0; r < n; ++r) {
        zv[r] = 0.0;
        if (col[r] == 0 && invd[r] > 0.0)
            zv[r] = bv[r] * invd[r];
    }
""")
def smooth_from_zero_rows(inverse_diag: wp.array(dtype=f64), colour: wp.array(dtype=wp.int32),
                          b: wp.array(dtype=f64), z: wp.array(dtype=f64)):
    ...


@wp.kernel
def mg_smooth_from_zero_kernel(
    inverse_diag: wp.array(dtype=f64),
    colour: wp.array(dtype=wp.int32),
    b: wp.array(dtype=f64),
    # outputs
    z: wp.array(dtype=f64),
):
    """``kernels/gas.py`` ``mg_smooth_from_zero_kernel`` over every row (launch one thread)."""
    smooth_from_zero_rows(inverse_diag, colour, b, z)


@wp.func_native(_STENCIL + _ROW + """
    const int* __restrict__ par = parent.data;
    const double* __restrict__ bv = b.data;
    const double* __restrict__ zv = z.data;
    const int* __restrict__ col = colour.data;
    double* __restrict__ cb = c_b.data;
    int coarse = c_b.shape[0];
    int n = parent.shape[0];
    for (int C = 0; C < coarse; ++C)
        cb[C] = 0.0;
    // the fine rows in ascending order: each block's rows in the order of ``children`` (ascending within a block)
    for (int r = 0; r < n; ++r) {
        if (col[r] != last_colour || !(d[r] > 0.0)) {
            double ax = stencil_row(zv, r);
            double t1 = -1.0 * ax;
            double t2 = 1.0 * bv[r];
            double res = t1 + t2;
            cb[par[r]] = cb[par[r]] + res;
        }
    }
""")
def residual_restrict_rows(parent: wp.array(dtype=wp.int32), diag: wp.array(dtype=f64), coef: wp.array2d(dtype=f64),
                           neighbour: wp.array2d(dtype=wp.int32), b: wp.array(dtype=f64), z: wp.array(dtype=f64),
                           colour: wp.array(dtype=wp.int32), last_colour: int, c_b: wp.array(dtype=f64)):
    ...


@wp.kernel
def mg_residual_restrict_kernel(
    child_start: wp.array(dtype=wp.int32),
    children: wp.array(dtype=wp.int32),
    parent: wp.array(dtype=wp.int32),
    A: K.Stencil,
    b: wp.array(dtype=f64),
    z: wp.array(dtype=f64),
    colour: wp.array(dtype=wp.int32),
    last_colour: int,
    # outputs
    c_b: wp.array(dtype=f64),
):
    """``kernels/gas.py`` ``mg_residual_restrict_kernel`` (launch one thread): the fine rows streamed in order, each
    residual added to its block's sum (``children`` lists a block's rows ascending, so each sum takes the same terms
    in the same order as the Warp kernel's gather; a sequential pass instead of a gather through ``children``)."""
    residual_restrict_rows(parent, A.diag, A.coef, A.neighbour, b, z, colour, last_colour, c_b)


@wp.func_native("""
    const int* __restrict__ par = parent.data;
    const double* __restrict__ cz = c_z.data;
    double* __restrict__ zv = z.data;
    int n = z.shape[0];
    for (int r = 0; r < n; ++r) {
        double t = scale * cz[par[r]];
        zv[r] = zv[r] + t;
    }
""")
def prolong_rows(parent: wp.array(dtype=wp.int32), c_z: wp.array(dtype=f64), scale: f64, z: wp.array(dtype=f64)):
    ...


@wp.kernel
def mg_prolong_kernel(
    parent: wp.array(dtype=wp.int32),
    c_z: wp.array(dtype=f64),
    scale: f64,
    # outputs
    z: wp.array(dtype=f64),
):
    """``kernels/gas.py`` ``mg_prolong_kernel`` over every row (launch one thread)."""
    prolong_rows(parent, c_z, scale, z)


@wp.func_native("""
    const int* __restrict__ par = parent.data;
    const double* __restrict__ d = diag.data;
    const double* __restrict__ c = coef.data;
    const int* __restrict__ nb = neighbour.data;
    double* __restrict__ cd = c_diag.data;
    double* __restrict__ cc = c_coef.data;
    int* __restrict__ cn = c_neighbour.data;
    int coarse = c_diag.shape[0];
    int n = parent.shape[0];
    for (int C = 0; C < coarse; ++C) {
        cd[C] = 0.0;
        for (int m = 0; m < 6; ++m) {
            cc[6 * (size_t)C + m] = 0.0;
            cn[6 * (size_t)C + m] = C;
        }
    }
    // the fine rows in ascending order: each block's rows in the order of ``children`` (ascending within a block)
    for (int r = 0; r < n; ++r) {
        int C = par[r];
        double dc = cd[C];
        dc = dc + d[r];
        for (int m = 0; m < 6; ++m) {
            double cm = c[6 * (size_t)r + m];
            if (cm != 0.0) {
                int D = par[nb[6 * (size_t)r + m]];
                if (D == C) {
                    dc = dc - cm;
                } else {
                    cc[6 * (size_t)C + m] = cc[6 * (size_t)C + m] + cm;
                    cn[6 * (size_t)C + m] = D;
                }
            }
        }
        cd[C] = dc;
    }
""")
def coarsen_rows(child_start: wp.array(dtype=wp.int32), children: wp.array(dtype=wp.int32),
                 parent: wp.array(dtype=wp.int32), diag: wp.array(dtype=f64), coef: wp.array2d(dtype=f64),
                 neighbour: wp.array2d(dtype=wp.int32), c_diag: wp.array(dtype=f64), c_coef: wp.array2d(dtype=f64),
                 c_neighbour: wp.array2d(dtype=wp.int32)):
    ...


@wp.kernel
def mg_coarsen_kernel(
    child_start: wp.array(dtype=wp.int32),
    children: wp.array(dtype=wp.int32),
    parent: wp.array(dtype=wp.int32),
    A: K.Stencil,
    # outputs
    Ac: K.Stencil,
):
    """``kernels/gas.py`` ``mg_coarsen_kernel`` (launch one thread): the fine rows streamed in order, each added to its
    block's row (``children`` lists a block's rows ascending, so each coarse entry takes the same terms in the same
    order as the Warp kernel's gather through ``children``)."""
    coarsen_rows(child_start, children, parent, A.diag, A.coef, A.neighbour, Ac.diag, Ac.coef, Ac.neighbour)


# ----------------------------------------------------------------- semi-Lagrangian advection (the face kernels' blocks)


BATCH_LANES = 32
"""Entries per batch of the native advection and Smagorinsky loops. The advection takes its solved faces a batch at a
time through the back-trace's stages (positions, the face velocity, the midpoint's three trilinear samples, the
departure sample), so the compiler makes the arithmetic SIMD and the faces' independent gather -> division -> floor
-> gather chains overlap; rig, in-process paired A/B of the three axes (warm caches, load ~4.5), speed against one
face at a time: 8 lanes 0.95 (not vectorised as the wider batches are), 16 lanes 1.62, 32 lanes ~1.8, 64 lanes the
same as 32. Smagorinsky gathers each cell's neighbour differences, then divides, squares and takes the root over the
batch: 1.5x against one cell at a time. The same operations per entry in the same order: the same bits."""


@wp.func_native(r"""
    constexpr int LANES = BATCH_LANES;
    const int shape[3] = {g.shape.c[0], g.shape.c[1], g.shape.c[2]};
    const int periodic[3] = {g.periodic.c[0], g.periodic.c[1], g.periodic.c[2]};
    const float origin[3] = {g.origin.c[0], g.origin.c[1], g.origin.c[2]};
    const float h = g.spacing;
    const float* __restrict__ old[3] = {vel_old.x.data, vel_old.y.data, vel_old.z.data};
    const int* __restrict__ type = axis == 0 ? types.x.data : (axis == 1 ? types.y.data : types.z.data);
    float* __restrict__ out = axis == 0 ? vel_new.x.data : (axis == 1 ? vel_new.y.data : vel_new.z.data);
    const wp::vec_t<3, int>* __restrict__ list = faces.data;
    // strides of the face array of axis a (shape + e_a, C order): flat (i, j, k) = (i sy + j) sz + k, in int
    // (a face array holds fewer than 2^31 entries: checked where the launch is recorded)
    int sy[3], sz[3];
    for (int a = 0; a < 3; ++a) {
        sy[a] = shape[1] + (a == 1);
        sz[a] = shape[2] + (a == 2);
    }
    auto at = [&](int a, int i, int j, int k) -> int { return (i * sy[a] + j) * sz[a] + k; };
    auto clamp = [](int x, int lo, int hi) { return x < lo ? lo : (x > hi ? hi : x); };
    auto wrap = [](int x, int n) { return (x % n + n) % n; };
    // sample_axis over the lanes: s + add, its cell pair (clamped or wrapped) and weight
    auto sample_axis = [&](int a, int comp, const float* s, float add, int* lo, int* hi, float* w) {
        int n = shape[a];
        if (periodic[a] != 0) {
            for (int l = 0; l < LANES; ++l) {
                float sl = s[l] + add;
                float fl = floorf(sl);
                int b = (int)fl;
                lo[l] = wrap(b, n);
                hi[l] = wrap(b + 1, n);
                w[l] = sl - fl;
            }
        } else {
            int upper = a == comp ? n : n - 1;
            for (int l = 0; l < LANES; ++l) {
                float sl = s[l] + add;
                float fl = floorf(sl);
                int b = (int)fl;
                lo[l] = clamp(b, 0, upper);
                hi[l] = clamp(b + 1, 0, upper);
                w[l] = sl - fl;
            }
        }
    };
    // neighbour_pair over the lanes
    auto pair = [&](int a, const int* lo, int shift, int upper, int* p0, int* p1) {
        int n = shape[a];
        if (periodic[a] != 0) {
            for (int l = 0; l < LANES; ++l) {
                p0[l] = wrap(lo[l] + shift, n);
                p1[l] = wrap(lo[l] + shift + 1, n);
            }
        } else {
            for (int l = 0; l < LANES; ++l) {
                p0[l] = clamp(lo[l] + shift, 0, upper);
                p1[l] = clamp(lo[l] + shift + 1, 0, upper);
            }
        }
    };
    // trilinear over the lanes: corners in the order 000, 100, 010, ..., 111, each weight a product in x, y, z order
    auto trilinear = [&](int a, const int* i0, const int* i1, const float* wx, const int* j0, const int* j1,
                         const float* wy, const int* k0, const int* k1, const float* wz, float* result) {
        const float* __restrict__ v = old[a];
        for (int l = 0; l < LANES; ++l) {
            float ux = 1.0f - wx[l];
            float uy = 1.0f - wy[l];
            float uz = 1.0f - wz[l];
            int r0 = i0[l] * sy[a], r1 = i1[l] * sy[a];
            int b00 = (r0 + j0[l]) * sz[a], b10 = (r1 + j0[l]) * sz[a];
            int b01 = (r0 + j1[l]) * sz[a], b11 = (r1 + j1[l]) * sz[a];
            float r = 0.0f;
            float t;
            t = ux * uy; t = t * uz; t = t * v[b00 + k0[l]]; r = r + t;
            t = wx[l] * uy; t = t * uz; t = t * v[b10 + k0[l]]; r = r + t;
            t = ux * wy[l]; t = t * uz; t = t * v[b01 + k0[l]]; r = r + t;
            t = wx[l] * wy[l]; t = t * uz; t = t * v[b11 + k0[l]]; r = r + t;
            t = ux * uy; t = t * wz[l]; t = t * v[b00 + k1[l]]; r = r + t;
            t = wx[l] * uy; t = t * wz[l]; t = t * v[b10 + k1[l]]; r = r + t;
            t = ux * wy[l]; t = t * wz[l]; t = t * v[b01 + k1[l]]; r = r + t;
            t = wx[l] * wy[l]; t = t * wz[l]; t = t * v[b11 + k1[l]]; r = r + t;
            result[l] = r;
        }
    };
    // a 4-face mean 0.25 ((a + b) + (c + d)) of component a's faces (p, q, r, s flat)
    auto mean4 = [&](int a, int p, int q, int r, int s) {
        float ab = old[a][p] + old[a][q];
        float cd = old[a][r] + old[a][s];
        float sum = ab + cd;
        return 0.25f * sum;
    };
    const float half_dt = 0.5f * dt;
    // solved faces in batches of LANES, each stage of the back-trace over the batch (independent lanes: their
    // gather -> division -> floor -> gather chains overlap, and the arithmetic is SIMD); the same operations per
    // face as kernels/gas.py advect_one, in the same order
    alignas(64) int f[3][LANES];
    alignas(64) int self[LANES];
    int count = 0;
    auto run_batch = [&](int n) {
        for (int l = n; l < LANES; ++l) {  // pad with the last face (the same value written again)
            for (int c = 0; c < 3; ++c)
                f[c][l] = f[c][n - 1];
            self[l] = self[n - 1];
        }
        alignas(64) float x[3][LANES], vf[3][LANES], s[3][LANES], vm[3][LANES], w[6][LANES];
        alignas(64) int p0[3][LANES], p1[3][LANES], lo[6][LANES], hi[6][LANES];
        // face_position
        for (int c = 0; c < 3; ++c) {
            float e = 0.5f * (float)(axis == c);
            for (int l = 0; l < LANES; ++l) {
                float p = (float)f[c][l] + 0.5f;
                p = p - e;
                float q = h * p;
                x[c][l] = origin[c] + q;
            }
        }
        // velocity_at_face: the face's own component, the others the mean of the 4 faces around it
        const int b0 = axis == 0 ? 1 : 0, b1 = axis == 2 ? 1 : 2;  // the other axes, ascending
        pair(axis, f[axis], -1, shape[axis] - 1, p0[axis], p1[axis]);
        pair(b0, f[b0], 0, shape[b0], p0[b0], p1[b0]);
        pair(b1, f[b1], 0, shape[b1], p0[b1], p1[b1]);
        for (int l = 0; l < LANES; ++l)
            vf[axis][l] = old[axis][self[l]];
        for (int l = 0; l < LANES; ++l) {
            int i = f[0][l], j = f[1][l], k = f[2][l];
            int i0 = p0[0][l], i1 = p1[0][l], j0 = p0[1][l], j1 = p1[1][l], k0 = p0[2][l], k1 = p1[2][l];
            if (axis == 0) {
                vf[1][l] = mean4(1, at(1, i0, j0, k), at(1, i1, j0, k), at(1, i0, j1, k), at(1, i1, j1, k));
                vf[2][l] = mean4(2, at(2, i0, j, k0), at(2, i1, j, k0), at(2, i0, j, k1), at(2, i1, j, k1));
            } else if (axis == 1) {
                vf[0][l] = mean4(0, at(0, i0, j0, k), at(0, i0, j1, k), at(0, i1, j0, k), at(0, i1, j1, k));
                vf[2][l] = mean4(2, at(2, i, j0, k0), at(2, i, j1, k0), at(2, i, j0, k1), at(2, i, j1, k1));
            } else {
                vf[0][l] = mean4(0, at(0, i0, j, k0), at(0, i0, j, k1), at(0, i1, j, k0), at(0, i1, j, k1));
                vf[1][l] = mean4(1, at(1, i, j0, k0), at(1, i, j0, k1), at(1, i, j1, k0), at(1, i, j1, k1));
            }
        }
        // x_mid = x - (0.5 dt) v_face, in grid coordinates (x - origin) / h - 1/2
        for (int c = 0; c < 3; ++c)
            for (int l = 0; l < LANES; ++l) {
                float d = half_dt * vf[c][l];
                float xm = x[c][l] - d;
                float t = xm - origin[c];
                t = t / h;
                s[c][l] = t - 0.5f;
            }
        // sample_velocity at x_mid: cell-centred pairs (lo/hi 0-2) and face pairs (3-5) on each axis
        for (int c = 0; c < 3; ++c) {
            sample_axis(c, -1, s[c], 0.0f, lo[c], hi[c], w[c]);
            sample_axis(c, c, s[c], 0.5f, lo[3 + c], hi[3 + c], w[3 + c]);
        }
        trilinear(0, lo[3], hi[3], w[3], lo[1], hi[1], w[1], lo[2], hi[2], w[2], vm[0]);
        trilinear(1, lo[0], hi[0], w[0], lo[4], hi[4], w[4], lo[2], hi[2], w[2], vm[1]);
        trilinear(2, lo[0], hi[0], w[0], lo[1], hi[1], w[1], lo[5], hi[5], w[5], vm[2]);
        // x_dep = x - dt v_mid; sample_component of the face's axis there
        for (int c = 0; c < 3; ++c)
            for (int l = 0; l < LANES; ++l) {
                float d = dt * vm[c][l];
                float xd = x[c][l] - d;
                float t = xd - origin[c];
                t = t / h;
                s[c][l] = t - 0.5f;
            }
        for (int c = 0; c < 3; ++c)
            sample_axis(c, axis, s[c], 0.5f * (float)(axis == c), lo[c], hi[c], w[c]);
        alignas(64) float result[LANES];
        trilinear(axis, lo[0], hi[0], w[0], lo[1], hi[1], w[1], lo[2], hi[2], w[2], result);
        for (int l = 0; l < LANES; ++l)
            out[self[l]] = result[l];
    };
    for (int index = first; index < last; ++index) {
        int i = list[index].c[0], j = list[index].c[1], k = list[index].c[2];
        int flat = at(axis, i, j, k);
        int t = type[flat];
        if (!(t == 1 || t == 3)) {  // not solved (FACE_FLUID, FACE_OUTLET): keeps its value
            out[flat] = old[axis][flat];
            continue;
        }
        f[0][count] = i; f[1][count] = j; f[2][count] = k; self[count] = flat;
        if (++count == LANES) {
            run_batch(LANES);
            count = 0;
        }
    }
    if (count)
        run_batch(count);
""".replace("BATCH_LANES", str(BATCH_LANES)))
def advect_faces(g: K.GridInfo, axis: int, faces: wp.array(dtype=wp.vec3i), types: K.FaceInt, vel_old: K.FaceFloat,
                 dt: float, vel_new: K.FaceFloat, first: int, last: int):
    """``kernels/gas.py`` ``advect_one`` for the entries [first, last) of ``faces``."""
    ...


def _advect_kernel(axis_constant: int):
    def advect_kernel(
        block: int,
        g: K.GridInfo,
        faces: wp.array(dtype=wp.vec3i),
        types: K.FaceInt,
        vel_old: K.FaceFloat,
        dt: float,
        # outputs
        vel_new: K.FaceFloat,
    ):
        """``kernels/gas.py`` ``ADVECT_KERNELS[axis]``: ``block`` consecutive entries of ``faces`` per thread."""
        t = wp.tid()
        advect_faces(g, wp.static(axis_constant), faces, types, vel_old, dt, vel_new, t * block,
                     wp.min(faces.shape[0], (t + 1) * block))

    return advect_kernel


ADVECT_KERNELS = K.per_axis_kernels(_advect_kernel, __name__)
"""``kernels/gas.py`` ``ADVECT_KERNELS``' native versions (same launch, same bits)."""


# ----------------------------------------------------------------- the projection's cell pass (block entries per thread)

_GRID = """
    const int shape[3] = {g.shape.c[0], g.shape.c[1], g.shape.c[2]};
    const int periodic[3] = {g.periodic.c[0], g.periodic.c[1], g.periodic.c[2]};
    // flat index of face (i, j, k) in the face array of axis a (shape + e_a, C order); of cell (i, j, k)
    auto at = [&](int a, int i, int j, int k) -> size_t {
        size_t sy = (size_t)(shape[1] + (a == 1));
        size_t sz = (size_t)(shape[2] + (a == 2));
        return ((size_t)i * sy + (size_t)j) * sz + (size_t)k;
    };
    auto cell_at = [&](int i, int j, int k) -> size_t {
        return ((size_t)i * (size_t)shape[1] + (size_t)j) * (size_t)shape[2] + (size_t)k;
    };
"""


@wp.func_native(_GRID + """
    const wp::vec_t<3, int>* __restrict__ list = cells.data;
    const int* __restrict__ fluid = cell_fluid.data;
    const int* __restrict__ type[3] = {types.x.data, types.y.data, types.z.data};
    const float* __restrict__ gp[3] = {face_grad_p.x.data, face_grad_p.y.data, face_grad_p.z.data};
    const float* __restrict__ v[3] = {vel.x.data, vel.y.data, vel.z.data};
    const double* __restrict__ pv = p.data;
    float* __restrict__ out_p = cell_pressure.data;
    wp::vec_t<3, float>* __restrict__ out_grad = cell_grad_p.data;
    wp::vec_t<3, float>* __restrict__ out_u = cell_velocity.data;
    const float minus_rho = -params.rho;
    for (int index = first; index < last; ++index) {
        int c[3] = {list[index].c[0], list[index].c[1], list[index].c[2]};
        size_t cell = cell_at(c[0], c[1], c[2]);
        float grad[3];
        float u[3] = {0.0f, 0.0f, 0.0f};
        for (int a = 0; a < 3; ++a)
            grad[a] = minus_rho * params.body_accel.c[a];
        float pressure = 0.0f;
        if (fluid[cell] != 0) {
            for (int a = 0; a < 3; ++a) {
                int hi[3] = {c[0], c[1], c[2]};
                hi[a] = hi[a] + 1;
                if (periodic[a] != 0 && hi[a] >= shape[a])  // wrap_face: the alias face is face 0
                    hi[a] = (hi[a] % shape[a] + shape[a]) % shape[a];
                size_t lo_face = at(a, c[0], c[1], c[2]);
                size_t hi_face = at(a, hi[0], hi[1], hi[2]);
                float sum = v[a][lo_face] + v[a][hi_face];
                u[a] = 0.5f * sum;
                float acc = 0.0f;
                float n = 0.0f;
                int t_lo = type[a][lo_face];
                if (t_lo == 1 || t_lo == 3) {
                    acc = acc + gp[a][lo_face];
                    n = n + 1.0f;
                }
                int t_hi = type[a][hi_face];
                if (t_hi == 1 || t_hi == 3) {
                    acc = acc + gp[a][hi_face];
                    n = n + 1.0f;
                }
                if (n > 0.0f) {
                    float mean = acc / n;
                    grad[a] = grad[a] + mean;
                }
            }
            pressure = (float)pv[cell];
        }
        out_p[cell] = pressure;
        out_grad[cell] = wp::vec_t<3, float>(grad[0], grad[1], grad[2]);
        out_u[cell] = wp::vec_t<3, float>(u[0], u[1], u[2]);
        if (!(wp::isfinite(u[0]) && wp::isfinite(u[1]) && wp::isfinite(u[2]) && wp::isfinite(pressure)))
            bad_count.data[0] += 1;
    }
""")
def cell_projected_cells(g: K.GridInfo, params: K.FlowParams, cells: wp.array(dtype=wp.vec3i),
                         cell_fluid: wp.array3d(dtype=wp.int32), types: K.FaceInt, face_grad_p: K.FaceFloat,
                         p: wp.array(dtype=f64), vel: K.FaceFloat, cell_pressure: wp.array3d(dtype=float),
                         cell_grad_p: wp.array3d(dtype=wp.vec3), cell_velocity: wp.array3d(dtype=wp.vec3),
                         bad_count: wp.array(dtype=wp.int32), first: int, last: int):
    """``kernels/gas.py`` ``cell_projected_one`` for the entries [first, last) of ``cells``."""
    ...


@wp.kernel
def cell_projected_kernel(
    block: int,
    g: K.GridInfo,
    params: K.FlowParams,
    cells: wp.array(dtype=wp.vec3i),
    cell_fluid: wp.array3d(dtype=wp.int32),
    types: K.FaceInt,
    face_grad_p: K.FaceFloat,
    p: wp.array(dtype=f64),
    vel: K.FaceFloat,
    # outputs
    cell_pressure: wp.array3d(dtype=float),
    cell_grad_p: wp.array3d(dtype=wp.vec3),
    cell_velocity: wp.array3d(dtype=wp.vec3),
    bad_count: wp.array(dtype=wp.int32),
):
    """``kernels/gas.py`` ``cell_projected_kernel``: ``block`` consecutive entries of ``cells`` per thread."""
    t = wp.tid()
    cell_projected_cells(g, params, cells, cell_fluid, types, face_grad_p, p, vel, cell_pressure, cell_grad_p,
                         cell_velocity, bad_count, t * block, wp.min(cells.shape[0], (t + 1) * block))


@wp.func_native(_GRID + """
    const wp::vec_t<3, int>* __restrict__ list = cells.data;
    const int* __restrict__ row_of = cell_row.data;
    const int* __restrict__ fluid = cell_fluid.data;
    const int* __restrict__ type[3] = {types.x.data, types.y.data, types.z.data};
    const float* __restrict__ outlet_p[3] = {bc.pressure.x.data, bc.pressure.y.data, bc.pressure.z.data};
    const float* __restrict__ eps_face[3] = {face_eps.x.data, face_eps.y.data, face_eps.z.data};
    const float* __restrict__ v[3] = {vel.x.data, vel.y.data, vel.z.data};
    const float* __restrict__ eps_now = cell_eps_f.data;
    const float* __restrict__ eps_before = cell_eps_f_prev.data;
    double* __restrict__ b_out = rhs.data;
    double* __restrict__ diag_out = A.diag.data;
    double* __restrict__ coef_out = A.coef.data;
    int* __restrict__ act = active.data;
    double* __restrict__ sums = fluid_sum.data;
    const double h = (double)g.spacing;
    for (int index = first; index < last; ++index) {
        int c[3] = {list[index].c[0], list[index].c[1], list[index].c[2]};
        size_t cell = cell_at(c[0], c[1], c[2]);
        int row = row_of[cell];
        if (row < 0)
            continue;
        act[row] = 0;
        double div = 0.0;
        double gross = 0.0;
        double b = 0.0;
        double a_diag = 0.0;
        for (int a = 0; a < 3; ++a) {
            for (int side = 0; side < 2; ++side) {
                int f[3] = {c[0], c[1], c[2]};
                f[a] = f[a] + side;
                if (periodic[a] != 0 && f[a] >= shape[a])  // wrap_face: the alias face is face 0
                    f[a] = (f[a] % shape[a] + shape[a]) % shape[a];
                size_t face = at(a, f[0], f[1], f[2]);
                double sign = (double)(2 * side - 1);
                double eps = (double)eps_face[a][face];
                double flux = eps * (double)v[a][face];
                double signed_flux = sign * flux;
                div = div + signed_flux;
                gross = gross + fabs(flux);
                int t = type[a][face];
                double coef = 0.0;
                if (t == 1 && fluid[cell] != 0) {
                    a_diag = a_diag + eps;
                    coef = eps;
                } else if (t == 3) {
                    double twice = 2.0 * eps;
                    a_diag = a_diag + twice;
                    float weighted = outlet_weight * outlet_p[a][face];
                    double term = twice * (double)weighted;
                    b = b + term;
                }
                coef_out[6 * (size_t)row + 2 * a + side] = coef;
            }
        }
        div = div / h;
        gross = gross / h;
        float change = eps_now[cell] - eps_before[cell];
        double d_eps_dt = (double)change / (double)params.dt;
        double scale = (double)params.rho * h;
        scale = scale * h;
        scale = scale / (double)params.dt;
        double source = div + d_eps_dt;
        double term = scale * source;
        b = b - term;
        if (a_diag == 0.0) {  // enclosed fluid cell: nothing can flow, keep p = 0
            b_out[row] = 0.0;
            diag_out[row] = 1.0;
            continue;
        }
        b_out[row] = b;
        diag_out[row] = a_diag;
        act[row] = 1;
        sums[0] = sums[0] + b;
        sums[1] = sums[1] + 1.0;
        gross = scale * gross;
        double gross2 = gross * gross;
        sums[2] = sums[2] + gross2;
    }
""")
def pressure_rhs_cells(g: K.GridInfo, params: K.FlowParams, cells: wp.array(dtype=wp.vec3i),
                       cell_row: wp.array(dtype=wp.int32), cell_fluid: wp.array3d(dtype=wp.int32), types: K.FaceInt,
                       bc: K.FaceBc, face_eps: K.FaceFloat, vel: K.FaceFloat, cell_eps_f: wp.array3d(dtype=float),
                       cell_eps_f_prev: wp.array3d(dtype=float), outlet_weight: float, rhs: wp.array(dtype=f64),
                       A: K.Stencil, active: wp.array(dtype=wp.int32), fluid_sum: wp.array(dtype=f64), first: int,
                       last: int):
    """``kernels/gas.py`` ``pressure_rhs_one`` for the entries [first, last) of ``cells``."""
    ...


@wp.kernel
def pressure_rhs_kernel(
    block: int,
    g: K.GridInfo,
    params: K.FlowParams,
    cells: wp.array(dtype=wp.vec3i),
    cell_row: wp.array(dtype=wp.int32),
    cell_fluid: wp.array3d(dtype=wp.int32),
    types: K.FaceInt,
    bc: K.FaceBc,
    face_eps: K.FaceFloat,
    vel: K.FaceFloat,
    cell_eps_f: wp.array3d(dtype=float),
    cell_eps_f_prev: wp.array3d(dtype=float),
    outlet_weight: float,
    # outputs
    rhs: wp.array(dtype=f64),
    A: K.Stencil,
    active: wp.array(dtype=wp.int32),
    fluid_sum: wp.array(dtype=f64),
):
    """``kernels/gas.py`` ``pressure_rhs_kernel``: ``block`` consecutive entries of ``cells`` per thread (the sums in
    ``fluid_sum`` added in the same order)."""
    t = wp.tid()
    pressure_rhs_cells(g, params, cells, cell_row, cell_fluid, types, bc, face_eps, vel, cell_eps_f, cell_eps_f_prev,
                       outlet_weight, rhs, A, active, fluid_sum, t * block, wp.min(cells.shape[0], (t + 1) * block))


@wp.func_native(_GRID + r"""
    constexpr int LANES = BATCH_LANES;
    const wp::vec_t<3, int>* __restrict__ list = cells.data;
    const int* __restrict__ fluid = cell_fluid.data;
    const wp::vec_t<3, float>* __restrict__ u = cell_velocity.data;
    const float* __restrict__ eps = cell_eps_f.data;
    float* __restrict__ nu_out = cell_nu_t.data;
    float* __restrict__ kappa_out = cell_kappa.data;
    const float h = g.spacing;
    const float two_h = 2.0f * h;
    const float length = params.smagorinsky * h;
    const float length2 = length * length;
    // cells in batches of LANES: the neighbours' differences gathered per cell, then the gradient's divisions, the
    // strain rate and its square root over the batch (SIMD); the same operations per cell in the same order
    for (int base = first; base < last; base += LANES) {
        int n = last - base < LANES ? last - base : LANES;
        alignas(64) float diff[3][3][LANES];
        alignas(64) size_t at_cell[LANES];
        for (int l = 0; l < LANES; ++l) {
            int index = base + (l < n ? l : n - 1);  // pad with the last cell (the same values written again)
            int c[3] = {list[index].c[0], list[index].c[1], list[index].c[2]};
            at_cell[l] = cell_at(c[0], c[1], c[2]);
            for (int d = 0; d < 3; ++d) {
                // cell_value: the neighbour along d (wrapped on a periodic axis), the cell itself beyond a wall
                int up[3] = {c[0], c[1], c[2]};
                int down[3] = {c[0], c[1], c[2]};
                up[d] = up[d] + 1;
                down[d] = down[d] - 1;
                int nd = shape[d];
                if (up[d] >= nd) {
                    if (periodic[d] != 0)
                        up[d] = (up[d] % nd + nd) % nd;
                    else
                        up[d] = c[d];
                }
                if (down[d] < 0) {
                    if (periodic[d] != 0)
                        down[d] = (down[d] % nd + nd) % nd;
                    else
                        down[d] = c[d];
                }
                const wp::vec_t<3, float>& vu = u[cell_at(up[0], up[1], up[2])];
                const wp::vec_t<3, float>& vd = u[cell_at(down[0], down[1], down[2])];
                for (int a = 0; a < 3; ++a)
                    diff[a][d][l] = vu.c[a] - vd.c[a];
            }
        }
        alignas(64) float nu[LANES];
        for (int l = 0; l < LANES; ++l) {
            float grad[3][3];
            for (int a = 0; a < 3; ++a)
                for (int d = 0; d < 3; ++d)
                    grad[a][d] = diff[a][d][l] / two_h;
            float ss = 0.0f;
            for (int a = 0; a < 3; ++a) {
                for (int d = 0; d < 3; ++d) {
                    float sum = grad[a][d] + grad[d][a];
                    float strain = 0.5f * sum;
                    float square = strain * strain;
                    ss = ss + square;
                }
            }
            float twice = 2.0f * ss;
            nu[l] = length2 * wp::sqrt(twice);
        }
        for (int l = 0; l < LANES; ++l) {
            size_t cell = at_cell[l];
            float nu_t = nu[l];
            if (fluid[cell] == 0)
                nu_t = 0.0f;
            nu_out[cell] = nu_t;
            float turbulent = params.rho * nu_t;
            float mu_eff = params.mu + turbulent;
            kappa_out[cell] = eps[cell] * mu_eff;
        }
    }
""".replace("BATCH_LANES", str(BATCH_LANES)))
def smagorinsky_cells(g: K.GridInfo, params: K.FlowParams, cells: wp.array(dtype=wp.vec3i),
                      cell_fluid: wp.array3d(dtype=wp.int32), cell_velocity: wp.array3d(dtype=wp.vec3),
                      cell_eps_f: wp.array3d(dtype=float), cell_nu_t: wp.array3d(dtype=float),
                      cell_kappa: wp.array3d(dtype=float), first: int, last: int):
    """``kernels/gas.py`` ``smagorinsky_one`` for the entries [first, last) of ``cells``."""
    ...


@wp.kernel
def smagorinsky_kernel(
    block: int,
    g: K.GridInfo,
    params: K.FlowParams,
    cells: wp.array(dtype=wp.vec3i),
    cell_fluid: wp.array3d(dtype=wp.int32),
    cell_velocity: wp.array3d(dtype=wp.vec3),
    cell_eps_f: wp.array3d(dtype=float),
    # outputs
    cell_nu_t: wp.array3d(dtype=float),
    cell_kappa: wp.array3d(dtype=float),
):
    """``kernels/gas.py`` ``smagorinsky_kernel``: ``block`` consecutive entries of ``cells`` per thread."""
    t = wp.tid()
    smagorinsky_cells(g, params, cells, cell_fluid, cell_velocity, cell_eps_f, cell_nu_t, cell_kappa, t * block,
                      wp.min(cells.shape[0], (t + 1) * block))


# ----------------------------------------------------------------- the viscous systems' assembly (face blocks)


@wp.func_native(_GRID + """
    const wp::vec_t<3, int>* __restrict__ list = faces.data;
    const int* __restrict__ row_of = face_row.data;
    const int* __restrict__ nflat = topology.neighbour_flat.data;
    const float* __restrict__ factors = topology.factor.data;
    const float* __restrict__ values = topology.value.data;
    const int* __restrict__ type = axis == 0 ? types.x.data : (axis == 1 ? types.y.data : types.z.data);
    const float* __restrict__ outlet_p = axis == 0 ? bc.pressure.x.data : (axis == 1 ? bc.pressure.y.data : bc.pressure.z.data);
    const int* __restrict__ fluid = cell_fluid.data;
    const float* __restrict__ eps_face = axis == 0 ? face_eps.x.data : (axis == 1 ? face_eps.y.data : face_eps.z.data);
    const float* __restrict__ kappa = face_kappa.data;
    const wp::vec_t<3, float>* __restrict__ source = cell_momentum_source.data;
    const double* __restrict__ pold = p_old.data;
    const float* __restrict__ adv = axis == 0 ? advected.x.data : (axis == 1 ? advected.y.data : advected.z.data);
    double* __restrict__ b_out = rhs.data;
    double* __restrict__ x0 = guess.data;
    double* __restrict__ diag_out = A.diag.data;
    double* __restrict__ coef_out = A.coef.data;
    const float h = g.spacing;
    const float rho = params.rho;
    const float dt = params.dt;
    // wrap_cell of (i, j, k): false when outside a non-periodic boundary
    auto wrap = [&](int* c) {
        for (int d = 0; d < 3; ++d) {
            int n = shape[d];
            if (c[d] < 0 || c[d] >= n) {
                if (periodic[d] != 0)
                    c[d] = (c[d] % n + n) % n;
                else
                    return false;
            }
        }
        return true;
    };
    for (int index = first; index < last; ++index) {
        int f[3] = {list[index].c[0], list[index].c[1], list[index].c[2]};
        size_t flat = at(axis, f[0], f[1], f[2]);
        int row = row_of[flat];
        if (row < 0)
            continue;
        // forced_velocity
        float u = adv[flat];
        int t = type[flat];
        float eps_f = eps_face[flat];
        float volume = h * h;
        volume = volume * h;
        if (t == 1) {
            int lo[3] = {f[0], f[1], f[2]};
            lo[axis] = lo[axis] - 1;
            int hi[3] = {f[0], f[1], f[2]};
            wrap(lo);
            wrap(hi);
            size_t c_lo = cell_at(lo[0], lo[1], lo[2]);
            size_t c_hi = cell_at(hi[0], hi[1], hi[2]);
            float impulse = 0.0f;
            float half = 0.5f * source[c_lo].c[axis];
            impulse = impulse + half;
            half = 0.5f * source[c_hi].c[axis];
            impulse = impulse + half;
            float body = dt * params.body_accel.c[axis];
            float density = rho * eps_f;
            density = density * volume;
            float kick = impulse / density;
            float increment = body + kick;
            u = u + increment;
            double dp = pold[c_hi] - pold[c_lo];
            float gradient = (float)dp / h;
            float ratio = dt / rho;
            float correction = ratio * gradient;
            u = u - correction;
        } else if (t == 3) {
            // momentum_source_increment
            float impulse = 0.0f;
            for (int side = 0; side < 2; ++side) {
                int c[3] = {f[0], f[1], f[2]};
                c[axis] = c[axis] - (1 - side);
                if (wrap(c)) {
                    size_t cell = cell_at(c[0], c[1], c[2]);
                    if (fluid[cell] != 0) {
                        float half = 0.5f * source[cell].c[axis];
                        impulse = impulse + half;
                    }
                }
            }
            float body = dt * params.body_accel.c[axis];
            float density = rho * eps_f;
            density = density * volume;
            float kick = impulse / density;
            float increment = body + kick;
            u = u + increment;
            // face_pressure_gradient at an outlet (weight 1)
            float p_out = 1.0f * outlet_p[flat];
            float difference;
            if (f[axis] == 0) {
                difference = (float)pold[cell_at(f[0], f[1], f[2])] - p_out;
            } else {
                int c[3] = {f[0], f[1], f[2]};
                c[axis] = c[axis] - 1;
                difference = p_out - (float)pold[cell_at(c[0], c[1], c[2])];
            }
            float twice = 2.0f * difference;
            float gradient = twice / h;
            float ratio = dt / rho;
            float correction = ratio * gradient;
            u = u - correction;
        }
        // viscous_rhs_one
        x0[row] = (double)u;
        float h2 = h * h;
        float mass = rho * eps_f;
        mass = mass / dt;
        float kappa_f = kappa[flat];
        float b = mass * u;
        float a_diag = mass;
        for (int m = 0; m < 6; ++m) {
            float coef = 0.0f;
            int neighbour = nflat[6 * (size_t)row + m];
            if (neighbour >= 0) {
                float sum = kappa_f + kappa[neighbour];
                sum = 0.5f * sum;
                coef = sum / h2;
                a_diag = a_diag + coef;
            } else {
                float factor = factors[6 * (size_t)row + m];
                if (factor > 0.0f) {
                    float fk = factor * kappa_f;
                    float term = fk / h2;
                    a_diag = a_diag + term;
                    float fkv = fk * values[6 * (size_t)row + m];
                    fkv = fkv / h2;
                    b = b + fkv;
                }
            }
            coef_out[6 * (size_t)row + m] = (double)coef;
        }
        b_out[row] = (double)b;
        diag_out[row] = (double)a_diag;
    }
""")
def viscous_rhs_faces(g: K.GridInfo, axis: int, params: K.FlowParams, faces: wp.array(dtype=wp.vec3i),
                      face_row: wp.array(dtype=wp.int32), topology: K.ViscousTopology, types: K.FaceInt,
                      bc: K.FaceBc, cell_fluid: wp.array3d(dtype=wp.int32), face_eps: K.FaceFloat,
                      face_kappa: wp.array(dtype=float), cell_momentum_source: wp.array3d(dtype=wp.vec3),
                      p_old: wp.array(dtype=f64), advected: K.FaceFloat, rhs: wp.array(dtype=f64),
                      guess: wp.array(dtype=f64), A: K.Stencil, first: int, last: int):
    """``kernels/gas.py`` ``viscous_rhs_one`` (with ``forced_velocity``) for the entries [first, last) of ``faces``."""
    ...


def _viscous_rhs_kernel(axis_constant: int):
    def viscous_rhs_kernel(
        block: int,
        g: K.GridInfo,
        params: K.FlowParams,
        faces: wp.array(dtype=wp.vec3i),
        face_row: wp.array(dtype=wp.int32),
        topology: K.ViscousTopology,
        types: K.FaceInt,
        bc: K.FaceBc,
        cell_fluid: wp.array3d(dtype=wp.int32),
        face_eps: K.FaceFloat,
        face_kappa: wp.array(dtype=float),
        cell_momentum_source: wp.array3d(dtype=wp.vec3),
        p_old: wp.array(dtype=f64),
        advected: K.FaceFloat,
        # outputs
        rhs: wp.array(dtype=f64),
        guess: wp.array(dtype=f64),
        A: K.Stencil,
    ):
        """``kernels/gas.py`` ``VISCOUS_RHS_KERNELS[axis]``: ``block`` consecutive entries of ``faces`` per thread."""
        t = wp.tid()
        viscous_rhs_faces(g, wp.static(axis_constant), params, faces, face_row, topology, types, bc, cell_fluid,
                          face_eps, face_kappa, cell_momentum_source, p_old, advected, rhs, guess, A, t * block,
                          wp.min(faces.shape[0], (t + 1) * block))

    return viscous_rhs_kernel


VISCOUS_RHS_KERNELS = K.per_axis_kernels(_viscous_rhs_kernel, __name__)
"""``kernels/gas.py`` ``VISCOUS_RHS_KERNELS``' native versions (same launch, same bits)."""


# ----------------------------------------------------------------- face coefficients, pressure correction (face blocks)

_WRAP = """
    // wrap_cell of (i, j, k) in place: false when outside a non-periodic boundary
    auto wrap = [&](int* c) {
        for (int d = 0; d < 3; ++d) {
            int n = shape[d];
            if (c[d] < 0 || c[d] >= n) {
                if (periodic[d] != 0)
                    c[d] = (c[d] % n + n) % n;
                else
                    return false;
            }
        }
        return true;
    };
"""


@wp.func_native(_GRID + _WRAP + """
    const wp::vec_t<3, int>* __restrict__ list = faces.data;
    const int* __restrict__ fluid = cell_fluid.data;
    const float* __restrict__ eps = cell_eps_f.data;
    const float* __restrict__ kap = cell_kappa.data;
    float* __restrict__ eps_out = axis == 0 ? face_eps.x.data : (axis == 1 ? face_eps.y.data : face_eps.z.data);
    float* __restrict__ kappa_out = axis == 0 ? face_kappa.x.data : (axis == 1 ? face_kappa.y.data : face_kappa.z.data);
    for (int index = first; index < last; ++index) {
        int f[3] = {list[index].c[0], list[index].c[1], list[index].c[2]};
        float eps_sum = 0.0f;
        float kappa_sum = 0.0f;
        float count = 0.0f;
        for (int side = 0; side < 2; ++side) {
            int c[3] = {f[0], f[1], f[2]};
            c[axis] = c[axis] - (1 - side);
            if (wrap(c)) {
                size_t cell = cell_at(c[0], c[1], c[2]);
                if (fluid[cell] != 0) {
                    eps_sum = eps_sum + eps[cell];
                    kappa_sum = kappa_sum + kap[cell];
                    count = count + 1.0f;
                }
            }
        }
        size_t face = at(axis, f[0], f[1], f[2]);
        if (count > 0.0f) {
            eps_out[face] = eps_sum / count;
            kappa_out[face] = kappa_sum / count;
        } else {
            eps_out[face] = 1.0f;
            kappa_out[face] = 0.0f;
        }
    }
""")
def face_coefficients_faces(g: K.GridInfo, axis: int, faces: wp.array(dtype=wp.vec3i),
                            cell_fluid: wp.array3d(dtype=wp.int32), cell_eps_f: wp.array3d(dtype=float),
                            cell_kappa: wp.array3d(dtype=float), face_eps: K.FaceFloat, face_kappa: K.FaceFloat,
                            first: int, last: int):
    """``kernels/gas.py`` ``face_coefficients_one`` for the entries [first, last) of ``faces``."""
    ...


def _face_coefficients_kernel(axis_constant: int):
    def face_coefficients_kernel(
        block: int,
        g: K.GridInfo,
        faces: wp.array(dtype=wp.vec3i),
        cell_fluid: wp.array3d(dtype=wp.int32),
        cell_eps_f: wp.array3d(dtype=float),
        cell_kappa: wp.array3d(dtype=float),
        # outputs
        face_eps: K.FaceFloat,
        face_kappa: K.FaceFloat,
    ):
        """``kernels/gas.py`` ``FACE_COEFFICIENTS_KERNELS[axis]``: ``block`` consecutive entries of ``faces`` per
        thread."""
        t = wp.tid()
        face_coefficients_faces(g, wp.static(axis_constant), faces, cell_fluid, cell_eps_f, cell_kappa, face_eps,
                                face_kappa, t * block, wp.min(faces.shape[0], (t + 1) * block))

    return face_coefficients_kernel


FACE_COEFFICIENTS_KERNELS = K.per_axis_kernels(_face_coefficients_kernel, __name__)
"""``kernels/gas.py`` ``FACE_COEFFICIENTS_KERNELS``' native versions (same launch, same bits)."""


@wp.func_native(_GRID + _WRAP + """
    const wp::vec_t<3, int>* __restrict__ list = faces.data;
    const int* __restrict__ type = axis == 0 ? types.x.data : (axis == 1 ? types.y.data : types.z.data);
    const float* __restrict__ outlet_p = axis == 0 ? bc.pressure.x.data : (axis == 1 ? bc.pressure.y.data : bc.pressure.z.data);
    const double* __restrict__ increment = p.data;
    const double* __restrict__ total = p_total.data;
    float* __restrict__ v = axis == 0 ? vel.x.data : (axis == 1 ? vel.y.data : vel.z.data);
    float* __restrict__ gp_out = axis == 0 ? face_grad_p.x.data : (axis == 1 ? face_grad_p.y.data : face_grad_p.z.data);
    const float h = g.spacing;
    for (int index = first; index < last; ++index) {
        int f[3] = {list[index].c[0], list[index].c[1], list[index].c[2]};
        size_t face = at(axis, f[0], f[1], f[2]);
        int t = type[face];
        if (!(t == 1 || t == 3))
            continue;
        // face_pressure_gradients
        float gp, gp_total;
        if (t == 1) {
            int lo[3] = {f[0], f[1], f[2]};
            lo[axis] = lo[axis] - 1;
            int hi[3] = {f[0], f[1], f[2]};
            wrap(lo);
            wrap(hi);
            size_t c_lo = cell_at(lo[0], lo[1], lo[2]);
            size_t c_hi = cell_at(hi[0], hi[1], hi[2]);
            double d_increment = increment[c_hi] - increment[c_lo];
            double d_total = total[c_hi] - total[c_lo];
            gp = (float)d_increment / h;
            gp_total = (float)d_total / h;
        } else {
            float p_out = outlet_p[face];
            float increment_out = outlet_weight * p_out;
            float total_out = 1.0f * p_out;
            float a, b;
            if (f[axis] == 0) {
                size_t inside = cell_at(f[0], f[1], f[2]);
                a = (float)increment[inside] - increment_out;
                b = (float)total[inside] - total_out;
            } else {
                int c[3] = {f[0], f[1], f[2]};
                c[axis] = c[axis] - 1;
                size_t inside = cell_at(c[0], c[1], c[2]);
                a = increment_out - (float)increment[inside];
                b = total_out - (float)total[inside];
            }
            a = 2.0f * a;
            b = 2.0f * b;
            gp = a / h;
            gp_total = b / h;
        }
        float ratio = params.dt / params.rho;
        float correction = ratio * gp;
        v[face] = v[face] - correction;
        gp_out[face] = gp_total;
    }
""")
def pressure_correct_faces(g: K.GridInfo, axis: int, params: K.FlowParams, faces: wp.array(dtype=wp.vec3i),
                           types: K.FaceInt, bc: K.FaceBc, p: wp.array(dtype=f64), outlet_weight: float,
                           p_total: wp.array(dtype=f64), vel: K.FaceFloat, face_grad_p: K.FaceFloat, first: int,
                           last: int):
    """``kernels/gas.py`` ``pressure_correct_one`` for the entries [first, last) of ``faces``."""
    ...


def _pressure_correct_kernel(axis_constant: int):
    def pressure_correct_kernel(
        block: int,
        g: K.GridInfo,
        params: K.FlowParams,
        faces: wp.array(dtype=wp.vec3i),
        types: K.FaceInt,
        bc: K.FaceBc,
        p: wp.array(dtype=f64),
        outlet_weight: float,
        p_total: wp.array(dtype=f64),
        # outputs
        vel: K.FaceFloat,
        face_grad_p: K.FaceFloat,
    ):
        """``kernels/gas.py`` ``PRESSURE_CORRECT_KERNELS[axis]``: ``block`` consecutive entries of ``faces`` per
        thread."""
        t = wp.tid()
        pressure_correct_faces(g, wp.static(axis_constant), params, faces, types, bc, p, outlet_weight, p_total, vel,
                               face_grad_p, t * block, wp.min(faces.shape[0], (t + 1) * block))

    return pressure_correct_kernel


PRESSURE_CORRECT_KERNELS = K.per_axis_kernels(_pressure_correct_kernel, __name__)
"""``kernels/gas.py`` ``PRESSURE_CORRECT_KERNELS``' native versions (same launch, same bits)."""


# ----------------------------------------------------------------- small cell and face passes (blocks)


@wp.func_native(_GRID + """
    const wp::vec_t<3, int>* __restrict__ list = cells.data;
    const float* __restrict__ eps_s = cell_eps_s.data;
    const int* __restrict__ fluid = cell_fluid.data;
    const float* __restrict__ v[3] = {vel.x.data, vel.y.data, vel.z.data};
    float* __restrict__ eps_out = cell_eps_f.data;
    wp::vec_t<3, float>* __restrict__ u_out = cell_velocity.data;
    for (int index = first; index < last; ++index) {
        int c[3] = {list[index].c[0], list[index].c[1], list[index].c[2]};
        size_t cell = cell_at(c[0], c[1], c[2]);
        // eps_f_one
        if (fluid[cell] != 0) {
            float free = 1.0f - eps_s[cell];
            eps_out[cell] = wp::clamp(free, eps_min, 1.0f);
        } else {
            eps_out[cell] = 1.0f;
        }
        // cell_velocity_one
        float u[3] = {0.0f, 0.0f, 0.0f};
        if (fluid[cell] != 0) {
            for (int a = 0; a < 3; ++a) {
                int hi[3] = {c[0], c[1], c[2]};
                hi[a] = hi[a] + 1;
                if (periodic[a] != 0 && hi[a] >= shape[a])  // wrap_face: the alias face is face 0
                    hi[a] = (hi[a] % shape[a] + shape[a]) % shape[a];
                float sum = v[a][at(a, c[0], c[1], c[2])] + v[a][at(a, hi[0], hi[1], hi[2])];
                u[a] = 0.5f * sum;
            }
        }
        u_out[cell] = wp::vec_t<3, float>(u[0], u[1], u[2]);
    }
""")
def cell_state_cells(g: K.GridInfo, cells: wp.array(dtype=wp.vec3i), cell_eps_s: wp.array3d(dtype=float),
                     cell_fluid: wp.array3d(dtype=wp.int32), eps_min: float, vel: K.FaceFloat,
                     cell_eps_f: wp.array3d(dtype=float), cell_velocity: wp.array3d(dtype=wp.vec3), first: int,
                     last: int):
    """``kernels/gas.py`` ``eps_f_one`` and ``cell_velocity_one`` for the entries [first, last) of ``cells``."""
    ...


@wp.kernel
def cell_state_kernel(
    block: int,
    g: K.GridInfo,
    cells: wp.array(dtype=wp.vec3i),
    cell_eps_s: wp.array3d(dtype=float),
    cell_fluid: wp.array3d(dtype=wp.int32),
    eps_min: float,
    vel: K.FaceFloat,
    # outputs
    cell_eps_f: wp.array3d(dtype=float),
    cell_velocity: wp.array3d(dtype=wp.vec3),
):
    """``kernels/gas.py`` ``cell_state_kernel``: ``block`` consecutive entries of ``cells`` per thread."""
    t = wp.tid()
    cell_state_cells(g, cells, cell_eps_s, cell_fluid, eps_min, vel, cell_eps_f, cell_velocity, t * block,
                     wp.min(cells.shape[0], (t + 1) * block))


@wp.func_native(_GRID + """
    const wp::vec_t<3, int>* __restrict__ list = faces.data;
    const int* __restrict__ row_of = face_row.data;
    const double* __restrict__ xv = x.data;
    float* __restrict__ v = axis == 0 ? vel.x.data : (axis == 1 ? vel.y.data : vel.z.data);
    for (int index = first; index < last; ++index) {
        size_t face = at(axis, list[index].c[0], list[index].c[1], list[index].c[2]);
        int row = row_of[face];
        if (row >= 0)
            v[face] = (float)xv[row];
    }
""")
def store_component_faces(g: K.GridInfo, axis: int, faces: wp.array(dtype=wp.vec3i),
                          face_row: wp.array(dtype=wp.int32), x: wp.array(dtype=f64), vel: K.FaceFloat, first: int,
                          last: int):
    """``kernels/gas.py`` ``store_component_one`` for the entries [first, last) of ``faces``."""
    ...


def _store_component_kernel(axis_constant: int):
    def store_component_kernel(
        block: int,
        g: K.GridInfo,
        faces: wp.array(dtype=wp.vec3i),
        face_row: wp.array(dtype=wp.int32),
        x: wp.array(dtype=f64),
        # outputs
        vel: K.FaceFloat,
    ):
        """``kernels/gas.py`` ``STORE_COMPONENT_KERNELS[axis]``: ``block`` consecutive entries of ``faces`` per
        thread."""
        t = wp.tid()
        store_component_faces(g, wp.static(axis_constant), faces, face_row, x, vel, t * block,
                              wp.min(faces.shape[0], (t + 1) * block))

    return store_component_kernel


STORE_COMPONENT_KERNELS = K.per_axis_kernels(_store_component_kernel, __name__)
"""``kernels/gas.py`` ``STORE_COMPONENT_KERNELS``' native versions (same launch, same bits)."""


@wp.func_native(_GRID + """
    const wp::vec_t<3, int>* __restrict__ list = cells.data;
    const int* __restrict__ row_of = cell_row.data;
    const double* __restrict__ xv = x.data;
    double* __restrict__ dp = increment.data;
    double* __restrict__ p = total.data;
    for (int index = first; index < last; ++index) {
        size_t cell = cell_at(list[index].c[0], list[index].c[1], list[index].c[2]);
        int row = row_of[cell];
        if (row >= 0) {
            dp[cell] = xv[row];
            p[cell] = p[cell] + xv[row];
        }
    }
""")
def pressure_increment_cells(g: K.GridInfo, cells: wp.array(dtype=wp.vec3i), cell_row: wp.array(dtype=wp.int32),
                             x: wp.array(dtype=f64), increment: wp.array(dtype=f64), total: wp.array(dtype=f64),
                             first: int, last: int):
    """``kernels/gas.py`` ``pressure_increment_one`` for the entries [first, last) of ``cells``."""
    ...


@wp.kernel
def pressure_increment_kernel(
    block: int,
    g: K.GridInfo,
    cells: wp.array(dtype=wp.vec3i),
    cell_row: wp.array(dtype=wp.int32),
    x: wp.array(dtype=f64),
    # outputs
    increment: wp.array(dtype=f64),
    total: wp.array(dtype=f64),
):
    """``kernels/gas.py`` ``pressure_increment_kernel``: ``block`` consecutive entries of ``cells`` per thread."""
    t = wp.tid()
    pressure_increment_cells(g, cells, cell_row, x, increment, total, t * block,
                             wp.min(cells.shape[0], (t + 1) * block))


ONE_THREAD = frozenset({"pcg_step_kernel", "pcg_direction_kernel", "jacobi_start_kernel", "rb_gather_kernel",
                        "rb_scatter_kernel", "rb_red_kernel", "ic0_factor_kernel",
                        "ic0_apply_kernel", "ic0_step_apply_kernel", "mg_smooth_kernel", "mg_smooth_from_zero_kernel",
                        "mg_residual_restrict_kernel", "mg_prolong_kernel", "mg_coarsen_kernel"})
"""The kernels here whose one thread runs every row (launch ``dim=1``); the others keep their Warp launch dims."""

_NATIVE = ("pcg_matvec_dot_kernel", "pcg_residual_start_kernel", "pcg_dot_pair_kernel", "jacobi_step_dot_kernel",
           "rb_black_matvec_dot_kernel", "rb_black_residual_kernel",
           "cell_projected_kernel", "pressure_rhs_kernel", "smagorinsky_kernel",
           "cell_state_kernel", "pressure_increment_kernel", *sorted(ONE_THREAD))


def for_device(kernel, dim: int, device, arguments) -> tuple:
    """(kernel, dim) to launch for ``kernel`` of ``kernels/gas.py`` over ``dim`` threads on ``device``: on the CPU this
    module's native version where there is one (its own dim), else ``kernel`` itself. The native loops take raw
    pointers, so every array among ``arguments`` (also inside a ``Stencil``) must be contiguous (checked here, when a
    launch is recorded)."""
    if not wp.get_device(device).is_cpu:
        return kernel, dim
    if kernel in K.ADVECT_KERNELS:
        native = ADVECT_KERNELS[K.ADVECT_KERNELS.index(kernel)]
    elif kernel in K.VISCOUS_RHS_KERNELS:
        native = VISCOUS_RHS_KERNELS[K.VISCOUS_RHS_KERNELS.index(kernel)]
    elif kernel in K.FACE_COEFFICIENTS_KERNELS:
        native = FACE_COEFFICIENTS_KERNELS[K.FACE_COEFFICIENTS_KERNELS.index(kernel)]
    elif kernel in K.PRESSURE_CORRECT_KERNELS:
        native = PRESSURE_CORRECT_KERNELS[K.PRESSURE_CORRECT_KERNELS.index(kernel)]
    elif kernel in K.STORE_COMPONENT_KERNELS:
        native = STORE_COMPONENT_KERNELS[K.STORE_COMPONENT_KERNELS.index(kernel)]
    elif getattr(K, kernel.key, None) is kernel and kernel.key in _NATIVE:
        native = globals()[kernel.key]
    else:
        return kernel, dim
    for value in arguments:
        if hasattr(value, "neighbour"):  # Stencil
            arrays = (value.diag, value.coef, value.neighbour)
        elif hasattr(value, "z") and hasattr(value, "y"):  # FaceFloat, FaceInt
            arrays = (value.x, value.y, value.z)
        elif hasattr(value, "pressure"):  # FaceBc: the native loops read its outlet pressure
            arrays = (value.pressure.x, value.pressure.y, value.pressure.z)
        elif hasattr(value, "neighbour_flat"):  # ViscousTopology
            arrays = (value.neighbour_flat, value.factor, value.value)
        else:
            arrays = (value,)
        for array in arrays:
            if isinstance(array, wp.array) and not array.is_contiguous:
                raise ValueError(f"{kernel.key}: the native CPU loop needs contiguous arrays")
            if native in ADVECT_KERNELS and isinstance(array, wp.array) and array.size >= 2**31:
                raise ValueError(f"{kernel.key}: the native CPU loop's flat indices are 32-bit: fewer than 2^31 "
                                 "entries per array")
    return native, 1 if kernel.key in ONE_THREAD else dim
