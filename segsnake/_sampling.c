/* Cubic B-spline value and exact gradient at points: the inner loop of segsnake.lookup.
 *
 * numpy's version of this kernel gathers 64 coefficients per point into a temporary and
 * contracts it in six einsum passes; it is memory-bound at 150-300 ns a point, and the flux
 * energy samples 10^4-10^5 points per evaluation. Here each point's 4x4x4 neighbourhood is read
 * in 16 runs of 4 contiguous coefficients and contracted in registers.
 *
 * The semantics are those documented in lookup.py (Lookup.sample): points in mm, divided by the
 * spacing; clamped to the grid box [0, n - 1] per axis with that gradient component set to 0
 * outside; a NaN or infinite coordinate gives NaN outputs. The coefficients are mirror-padded
 * by PAD = 2 on every side, so every index below is inside the padded array.
 *
 * Plain C on Python buffers (no numpy headers; float64 buffers, the coefficients float64 or
 * float32); the GIL
 * is released, so blocks of points run in parallel threads.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

#include "_buffers.h"

static void weights(double u, double w[4], double dw[4])
{
    double v = 1.0 - u, u2 = u * u, u3 = u2 * u;
    w[0] = v * v * v / 6.0;
    w[1] = (3.0 * u3 - 6.0 * u2 + 4.0) / 6.0;
    w[2] = (-3.0 * u3 + 3.0 * u2 + 3.0 * u + 1.0) / 6.0;
    w[3] = u3 / 6.0;
    dw[0] = -0.5 * v * v;
    dw[1] = 1.5 * u2 - 2.0 * u;
    dw[2] = -1.5 * u2 + u + 0.5;
    dw[3] = 0.5 * u2;
}

/* Compiled twice where the compiler and the C library dispatch at run time (GCC 6 or later on
 * x86-64 Linux with glibc, whose loader resolves the ifunc): for AVX2 and for the baseline, the
 * loader picking the one the CPU runs. The arithmetic is the same operations in the same order
 * either way (AVX2 does not enable FMA, and setup.py builds with -ffp-contract=off), so every
 * machine gives the same numbers (checked by hand: a 70 560-point sampling to the last bit, the
 * Colin27 brain's result to every digit of its energy); AVX2 only widens the loads and products
 * (a brain-sized float32 lookup: 100-110 -> 70-75 ns a point on a surface's quadrature nodes,
 * docs/benchmarks.md session 22). Elsewhere (clang, musl, Windows, other CPUs) one version. */
#if defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 6 && defined(__x86_64__) && \
    defined(__linux__) && defined(__GLIBC__)
#define DISPATCH __attribute__((target_clones("avx2", "default")))
#else
#define DISPATCH
#endif

/* Points ahead of the one being sampled whose coefficients are requested from memory first:
 * the kernel waits on its 16 scattered cache lines a point (a quadrature grid's nodes are near
 * each other, but a lookup is tens of MB). Measured on 61 740 nodes of a 21 x 21 brain surface
 * in a brain-sized float32 lookup, one thread, built as pip builds it (-O3): 114 ns a point
 * without, 80 with two ahead; at -O2 102 without, 92 one ahead, 80 two or four, 82 eight
 * (docs/benchmarks.md, session 27). A hint only: the numbers are the same to the bit. */
#define PREFETCH_AHEAD 2
#if defined(__GNUC__) || defined(__clang__)
#define PREFETCH(address) __builtin_prefetch((address), 0, 1)
#else
#define PREFETCH(address) ((void)(address))
#endif

#define DEFINE_SAMPLE_POINTS(NAME, CTYPE) \
DISPATCH \
static void NAME(const CTYPE *coef, const Py_ssize_t pshape[3], const Py_ssize_t shape[3], \
                          const double spacing[3], const double *pts, Py_ssize_t n, \
                          double *g_out, double *grad_out) \
{ \
    const Py_ssize_t sy = pshape[2], sx = pshape[1] * pshape[2]; \
    for (Py_ssize_t k = 0; k < n; k++) { \
        const double *p = pts + 3 * k; \
        if (k + PREFETCH_AHEAD < n) { \
            /* the 4 x 4 runs the point PREFETCH_AHEAD on will read (not beyond the grid, \
             * where its index would need the clamping below, nor for NaN) */ \
            const double *q = pts + 3 * (k + PREFETCH_AHEAD); \
            Py_ssize_t j[3]; \
            int inside = 1; \
            for (int d = 0; d < 3 && inside; d++) { \
                double t = q[d] / spacing[d]; \
                inside = t >= 0.0 && t <= (double)(shape[d] - 2); \
                j[d] = inside ? (Py_ssize_t)t : 0; \
            } \
            if (inside) { \
                const CTYPE *ahead = coef + (j[0] + 1) * sx + (j[1] + 1) * sy + (j[2] + 1); \
                for (int a = 0; a < 4; a++) \
                    for (int b = 0; b < 4; b++) \
                        PREFETCH(ahead + a * sx + b * sy); \
            } \
        } \
        double w[3][4], dw[3][4], scale[3]; \
        Py_ssize_t i0[3]; \
        int bad = 0; \
        for (int d = 0; d < 3; d++) { \
            double hi = (double)(shape[d] - 1); \
            double t = p[d] / spacing[d]; \
            if (!isfinite(t)) { /* NaN or Inf in, NaN out (a clamped value would look plausible) */ \
                bad = 1; \
                t = 0.0; \
            } \
            /* The gradient component is 0 along an axis where the point is clamped. */ \
            scale[d] = (t >= 0.0 && t <= hi) ? 1.0 / spacing[d] : 0.0; \
            t = t < 0.0 ? 0.0 : (t > hi ? hi : t); \
            double f = floor(t), top = hi - 1.0 > 0.0 ? hi - 1.0 : 0.0; \
            if (f > top) \
                f = top; \
            i0[d] = (Py_ssize_t)f; \
            weights(t - f, w[d], dw[d]); \
        } \
        if (bad) { \
            g_out[k] = NAN; \
            grad_out[3 * k] = grad_out[3 * k + 1] = grad_out[3 * k + 2] = NAN; \
            continue; \
        } \
        /* Padded index of the first of the four samples along each axis: i0 - 1 + PAD. */ \
        const CTYPE *base = coef + (i0[0] + 1) * sx + (i0[1] + 1) * sy + (i0[2] + 1); \
        double g = 0.0, gx = 0.0, gy = 0.0, gz = 0.0; \
        for (int a = 0; a < 4; a++) { \
            double czy = 0.0, czdy = 0.0, cdzy = 0.0; \
            for (int b = 0; b < 4; b++) { \
                const CTYPE *c = base + a * sx + b * sy; \
                double cz = c[0] * w[2][0] + c[1] * w[2][1] + c[2] * w[2][2] + c[3] * w[2][3]; \
                double cdz = c[0] * dw[2][0] + c[1] * dw[2][1] + c[2] * dw[2][2] + c[3] * dw[2][3]; \
                czy += cz * w[1][b]; \
                czdy += cz * dw[1][b]; \
                cdzy += cdz * w[1][b]; \
            } \
            g += czy * w[0][a]; \
            gx += czy * dw[0][a]; \
            gy += czdy * w[0][a]; \
            gz += cdzy * w[0][a]; \
        } \
        g_out[k] = g; \
        grad_out[3 * k] = gx * scale[0]; \
        grad_out[3 * k + 1] = gy * scale[1]; \
        grad_out[3 * k + 2] = gz * scale[2]; \
    } \
}

/* The coefficients in float64, or in float32 (half the memory of the region stages' lookups:
 * issue 18); the arithmetic is float64 either way. */
DEFINE_SAMPLE_POINTS(sample_points_f64, double)
DEFINE_SAMPLE_POINTS(sample_points_f32, float)

/* "f" for a float32 buffer, else "d" (its check then says what was expected); NULL with an
 * exception set when the object has no buffer. */
static const char *coef_format(PyObject *obj)
{
    Py_buffer view = {0};
    if (PyObject_GetBuffer(obj, &view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0)
        return NULL;
    const char *kind = strcmp(bare_format(&view), "f") == 0 ? "f" : "d";
    PyBuffer_Release(&view);
    return kind;
}

PyDoc_STRVAR(sample_doc,
"sample(coef, padded_shape, shape, spacing, points, g_out, grad_out)\n\n"
"Fill g_out (N,) and grad_out (N, 3) with the spline's value and gradient at points (N, 3).\n"
"All arrays are C-contiguous float64 except coef, float64 or float32; coef is mirror-padded by 2\n"
"(see lookup.Lookup).");

static PyObject *py_sample(PyObject *self, PyObject *args)
{
    PyObject *coef_obj, *pts_obj, *g_obj, *grad_obj;
    Py_buffer coef = {0}, pts = {0}, g = {0}, grad = {0};
    Py_ssize_t ps[3], sh[3];
    double spacing[3];
    if (!PyArg_ParseTuple(args, "O(nnn)(nnn)(ddd)OOO", &coef_obj, &ps[0], &ps[1], &ps[2],
                          &sh[0], &sh[1], &sh[2], &spacing[0], &spacing[1], &spacing[2], &pts_obj,
                          &g_obj, &grad_obj))
        return NULL;
    PyObject *result = NULL;
    Py_ssize_t size = 1;
    for (int d = 0; d < 3; d++) {
        /* shape >= 1, padded = shape + 4, and the padded size must not overflow */
        if (sh[d] < 1 || ps[d] != sh[d] + 4 || !(spacing[d] > 0.0) || ps[d] > PY_SSIZE_T_MAX / 8 / size) {
            PyErr_SetString(PyExc_ValueError,
                            "padded_shape must be shape + 4 (sizes that fit in memory) and spacing positive");
            return NULL;
        }
        size *= ps[d];
    }
    const char *kind = coef_format(coef_obj);
    if (kind == NULL || get_values(coef_obj, &coef, 0, size, kind, "coef") < 0)
        goto done;
    if (get_doubles(pts_obj, &pts, 0, -1, "points") < 0)
        goto done;
    Py_ssize_t n = pts.len / (3 * (Py_ssize_t)sizeof(double));
    if (pts.len != 3 * n * (Py_ssize_t)sizeof(double)) {
        PyErr_SetString(PyExc_ValueError, "points: expected (N, 3) float64 values");
        goto done;
    }
    if (get_doubles(g_obj, &g, 1, n, "g_out") < 0 || get_doubles(grad_obj, &grad, 1, 3 * n, "grad_out") < 0)
        goto done;
    Py_BEGIN_ALLOW_THREADS
    if (kind[0] == 'f')
        sample_points_f32((const float *)coef.buf, ps, sh, spacing, (const double *)pts.buf, n,
                          (double *)g.buf, (double *)grad.buf);
    else
        sample_points_f64((const double *)coef.buf, ps, sh, spacing, (const double *)pts.buf, n,
                          (double *)g.buf, (double *)grad.buf);
    Py_END_ALLOW_THREADS
    result = Py_None;
    Py_INCREF(result);
done:
    /* A view that was never filled has obj == NULL; PyBuffer_Release ignores it. */
    PyBuffer_Release(&coef);
    PyBuffer_Release(&pts);
    PyBuffer_Release(&g);
    PyBuffer_Release(&grad);
    return result;
}

static PyMethodDef methods[] = {
    {"sample", py_sample, METH_VARARGS, sample_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_sampling",
    "Compiled cubic B-spline sampling (value and gradient) for segsnake.lookup.", -1, methods,
};

PyMODINIT_FUNC PyInit__sampling(void)
{
    return PyModule_Create(&module);
}
