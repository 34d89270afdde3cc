/* The one-dimensional pass of segsnake.distance.distance_within: along one axis of a 3D grid,
 * the lower envelope of the parabolas f(q) + ((i - q) h)^2 (Felzenszwalb and Huttenlocher's
 * algorithm, "Distance transforms of sampled functions", Theory of Computing 8, 2012), in time
 * linear in the line's length.
 *
 * Each output is the chosen parabola's value as numpy's shifted minima computed it before:
 * out[i] = f[q] + (float)((a h)^2), a = |i - q|, the square in double rounded to float32, the sum
 * in float32. Where two parabolas tie to within rounding the envelope (its breakpoints in double)
 * may take the other (measured: one unit in the last place apart, in a few voxels per million
 * on grids of spacings 0.1, 1/3 or sqrt 2 mm; none on the brain's). A line without a finite value
 * is inf.
 * The brute-force minima over |a| <= R took 4.3 s of processor time in a brain's run (their
 * strided passes buffered by numpy), 2R + 1 passes per axis; this is one.
 *
 * Plain C on Python buffers (no numpy headers); the GIL is released, so that threads share the
 * lines of a pass (setup.py builds with -ffp-contract=off, as the other kernels).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdlib.h>

#include "_buffers.h"

/* One line: n values f (contiguous), the envelope into out (contiguous); v, z: work space of n
 * and n + 1. */
static void line_envelope(const float *f, float *out, Py_ssize_t n, double h, Py_ssize_t *v,
                          double *z)
{
    const double h2 = h * h;
    Py_ssize_t k = -1;
    for (Py_ssize_t q = 0; q < n; q++) {
        if (!isfinite(f[q]))
            continue; /* no parabola from here */
        const double fq = (double)f[q] + h2 * (double)q * (double)q;
        double x = -INFINITY;
        while (k >= 0) {
            const Py_ssize_t p = v[k];
            /* where the parabolas from p and q meet (in grid units along the line) */
            x = (fq - ((double)f[p] + h2 * (double)p * (double)p)) / (2.0 * h2 * (double)(q - p));
            if (x <= z[k])
                k--; /* p's parabola is nowhere lowest */
            else
                break;
        }
        k++;
        v[k] = q;
        z[k] = k == 0 ? -INFINITY : x;
    }
    if (k < 0) {
        for (Py_ssize_t i = 0; i < n; i++)
            out[i] = INFINITY;
        return;
    }
    z[k + 1] = INFINITY;
    Py_ssize_t j = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        while (z[j + 1] < (double)i)
            j++;
        const Py_ssize_t a = i > v[j] ? i - v[j] : v[j] - i;
        const double ah = (double)a * h;
        const float cost = (float)(ah * ah);
        out[i] = f[v[j]] + cost;
    }
}

PyDoc_STRVAR(envelope_doc,
"envelope(src, out, shape, axis, h, first, last)\n\n"
"Along array axis `axis` of the C-contiguous float32 arrays src and out (both of `shape`, 3\n"
"ints, not sharing memory), out[..., i, ...] = min over q of src[..., q, ...] + ((i - q) h)^2\n"
"(the squared distance pass; inf where the line has no finite value), for the lines first <=\n"
"L < last, L numbering the lines in C order of the two other axes. h > 0 (mm per voxel).");

static PyObject *py_envelope(PyObject *self, PyObject *args)
{
    PyObject *src_obj, *out_obj;
    Py_ssize_t n0, n1, n2, first, last;
    int axis;
    double h;
    if (!PyArg_ParseTuple(args, "OO(nnn)idnn", &src_obj, &out_obj, &n0, &n1, &n2, &axis, &h,
                          &first, &last))
        return NULL;
    if (n0 < 0 || n1 < 0 || n2 < 0 || axis < 0 || axis > 2 || !(h > 0) || !isfinite(h)) {
        PyErr_SetString(PyExc_ValueError,
                        "shape: expected 3 sizes >= 0, axis 0, 1 or 2, h a finite number > 0");
        return NULL;
    }
    if (n1 > 0 && n2 > 0 && n0 > PY_SSIZE_T_MAX / n1 / n2) {
        PyErr_SetString(PyExc_ValueError, "shape: too many voxels");
        return NULL;
    }
    const Py_ssize_t shape[3] = {n0, n1, n2};
    const Py_ssize_t stride[3] = {n1 * n2, n2, 1};
    const Py_ssize_t n = shape[axis];
    const Py_ssize_t lines = n > 0 ? n0 * n1 * n2 / n : 0;
    if (first < 0 || last > lines || first > last) {
        PyErr_Format(PyExc_ValueError, "lines %zd to %zd: expected 0 <= first <= last <= %zd",
                     first, last, lines);
        return NULL;
    }
    Py_buffer src = {0}, out = {0};
    if (get_values(src_obj, &src, 0, n0 * n1 * n2, "f", "src") < 0)
        return NULL;
    if (get_values(out_obj, &out, 1, n0 * n1 * n2, "f", "out") < 0) {
        PyBuffer_Release(&src);
        return NULL;
    }
    if (overlap(&src, &out)) {
        PyBuffer_Release(&src);
        PyBuffer_Release(&out);
        PyErr_SetString(PyExc_ValueError, "out shares memory with src");
        return NULL;
    }
    /* the other two axes, slow then fast: line L is (L / inner, L % inner) along them */
    const int slow = axis == 0 ? 1 : 0, fast = axis == 2 ? 1 : 2;
    const Py_ssize_t inner = shape[fast];
    const float *s = (const float *)src.buf;
    float *o = (float *)out.buf;
    int nomem = 0;
    Py_BEGIN_ALLOW_THREADS
    float *fl = malloc((n ? n : 1) * sizeof(float));
    float *ol = malloc((n ? n : 1) * sizeof(float));
    Py_ssize_t *v = malloc((n ? n : 1) * sizeof(Py_ssize_t));
    double *z = malloc((n + 1) * sizeof(double));
    if (fl == NULL || ol == NULL || v == NULL || z == NULL) {
        nomem = 1;
    } else {
        for (Py_ssize_t L = first; L < last; L++) {
            const Py_ssize_t base = (L / inner) * stride[slow] + (L % inner) * stride[fast];
            const Py_ssize_t step = stride[axis];
            for (Py_ssize_t i = 0; i < n; i++)
                fl[i] = s[base + i * step];
            line_envelope(fl, ol, n, h, v, z);
            for (Py_ssize_t i = 0; i < n; i++)
                o[base + i * step] = ol[i];
        }
    }
    free(fl);
    free(ol);
    free(v);
    free(z);
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&src);
    PyBuffer_Release(&out);
    if (nomem)
        return PyErr_NoMemory();
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"envelope", py_envelope, METH_VARARGS, envelope_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_distance",
    "Compiled lower envelope of parabolas (the squared distance transform's pass along an axis) "
    "for segsnake.distance.", -1, methods,
};

PyMODINIT_FUNC PyInit__distance(void)
{
    return PyModule_Create(&module);
}
