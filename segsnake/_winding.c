/* The range of a closed triangle mesh's winding numbers about the rays at integer (x, y),
 * parallel to z: the inner loop of segsnake.rasterize.windings.
 *
 * The region stages test every trial step's surface for self-crossings with it (a few hundred
 * to a few thousand times a run, on meshes of ~10^3 triangles); numpy's version of the same
 * scan conversion spent ~1 ms a test in the overhead of some forty small array operations.
 *
 * Each triangle's projection on (x, y) is scan-converted like segsnake.rasterize's numpy
 * version: a ray belongs to the triangle when it is strictly inside the projection, or on an
 * edge that the top-left rule gives it, the edge function computed from the edge's two vertices
 * in lexicographic order (so the two triangles that share an edge decide a ray on it the same
 * way). A crossing records its ray, its height and the sign of the projection's area (+1:
 * counter-clockwise, the face's normal along +z, the ray leaves). The crossings are bucketed by
 * ray, sorted by height within each ray, and the winding number runs along each ray, the
 * crossings at one height taken together.
 *
 * Plain C on a Python buffer (no numpy headers); the GIL is released.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

typedef struct {
    Py_ssize_t ray;
    double z;
    int up;
} Crossing;

/* The edge function of p -> q at (x, y), times `sign`, and whether (x, y) is on the triangle's
 * side of it (ties by the top-left rule); see rasterize._edge. */
static int edge(const double *p, const double *q, double x, double y, double sign, double *w)
{
    int swap = (q[0] < p[0]) || (q[0] == p[0] && q[1] < p[1]);
    const double *lo = swap ? q : p, *hi = swap ? p : q;
    double value = (hi[0] - lo[0]) * (y - lo[1]) - (hi[1] - lo[1]) * (x - lo[0]);
    if (swap)
        value = -value;
    double s = sign * value;
    double dx = sign * (q[0] - p[0]), dy = sign * (q[1] - p[1]);
    int takes = (dy < 0) || (dy == 0 && dx > 0);
    *w = s;
    return (s > 0) || (s == 0 && takes);
}

static int by_height(const void *a, const void *b)
{
    double za = ((const Crossing *)a)->z, zb = ((const Crossing *)b)->z;
    return (za > zb) - (za < zb);
}

/* 0 on success (lo, hi, excess set), -1 when out of memory. `tri`: f triangles of 3 vertices
 * (x, y, z), x and y >= 0. `excess`: the summed length, along the rays, of their stretches wound
 * other than 0 or 1 times, each weighted by how far beyond (|w| for w < 0, w - 1 for w > 1). */
static int winding(const double *tri, Py_ssize_t f, long *lo_out, long *hi_out,
                   double *excess_out)
{
    Py_ssize_t cap = 4 * f + 16, n = 0, nx = 1, ny = 1;
    for (Py_ssize_t t = 0; t < f; t++)
        for (int v = 0; v < 3; v++) {
            const double *p = tri + 9 * t + 3 * v;
            if (p[0] + 1 > nx)
                nx = (Py_ssize_t)floor(p[0]) + 1;
            if (p[1] + 1 > ny)
                ny = (Py_ssize_t)floor(p[1]) + 1;
        }
    Crossing *hits = malloc(cap * sizeof(Crossing));
    if (hits == NULL)
        return -1;
    for (Py_ssize_t t = 0; t < f; t++) {
        const double *a = tri + 9 * t, *b = a + 3, *c = a + 6;
        double area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
        if (area == 0)
            continue; /* a projection without area crosses no ray */
        double sign = area > 0 ? 1.0 : -1.0;
        double x0 = fmin(a[0], fmin(b[0], c[0])), x1 = fmax(a[0], fmax(b[0], c[0]));
        double y0 = fmin(a[1], fmin(b[1], c[1])), y1 = fmax(a[1], fmax(b[1], c[1]));
        for (Py_ssize_t i = (Py_ssize_t)ceil(x0); i <= (Py_ssize_t)floor(x1); i++)
            for (Py_ssize_t j = (Py_ssize_t)ceil(y0); j <= (Py_ssize_t)floor(y1); j++) {
                double wa, wb, wc;
                if (!edge(b, c, (double)i, (double)j, sign, &wa) ||
                    !edge(c, a, (double)i, (double)j, sign, &wb) ||
                    !edge(a, b, (double)i, (double)j, sign, &wc))
                    continue;
                if (n == cap) {
                    cap *= 2;
                    Crossing *more = realloc(hits, cap * sizeof(Crossing));
                    if (more == NULL) {
                        free(hits);
                        return -1;
                    }
                    hits = more;
                }
                hits[n].ray = i * ny + j;
                hits[n].z = (wa * a[2] + wb * b[2] + wc * c[2]) / (wa + wb + wc);
                hits[n].up = (int)sign;
                n++;
            }
    }
    /* Bucket by ray (a counting sort), then each ray's crossings by height. */
    Py_ssize_t rays = nx * ny;
    Py_ssize_t *start = calloc(rays + 1, sizeof(Py_ssize_t));
    Crossing *sorted = malloc((n ? n : 1) * sizeof(Crossing));
    if (start == NULL || sorted == NULL) {
        free(hits);
        free(start);
        free(sorted);
        return -1;
    }
    for (Py_ssize_t k = 0; k < n; k++)
        start[hits[k].ray + 1]++;
    for (Py_ssize_t r = 0; r < rays; r++)
        start[r + 1] += start[r];
    for (Py_ssize_t k = 0; k < n; k++)
        sorted[start[hits[k].ray]++] = hits[k];
    long lo = 0, hi = 0;
    double excess = 0.0;
    Py_ssize_t first = 0;
    for (Py_ssize_t r = 0; r < rays; r++) {
        /* (start[r] is now the end of ray r's crossings) */
        Py_ssize_t end = start[r];
        if (end - first > 1)
            qsort(sorted + first, end - first, sizeof(Crossing), by_height);
        long w = 0;
        for (Py_ssize_t k = first; k < end; k++) {
            w -= sorted[k].up;
            /* Crossings at one height are one event: a ray along a silhouette edge meets the
             * front and the back face there, leaving and entering at once. */
            if (k + 1 < end && sorted[k + 1].z == sorted[k].z)
                continue;
            if (w < lo)
                lo = w;
            if (w > hi)
                hi = w;
            /* up to the next crossing the ray is wound w times: beyond 0 or 1 counts */
            long beyond = w < 0 ? -w : (w > 1 ? w - 1 : 0);
            if (beyond && k + 1 < end)
                excess += (double)beyond * (sorted[k + 1].z - sorted[k].z);
        }
        first = end;
    }
    free(hits);
    free(start);
    free(sorted);
    *lo_out = lo;
    *hi_out = hi;
    *excess_out = excess;
    return 0;
}

PyDoc_STRVAR(windings_doc,
"windings(triangles) -> (lo, hi, excess)\n\n"
"The least and greatest winding number (0 counted) of a closed mesh about the rays at integer\n"
"(x, y), and the summed length of the rays' stretches wound beyond 0 or 1, times how far beyond:\n"
"triangles is a C-contiguous float64 array (F, 3, 3) of vertex coordinates, x, y >= 0.");

static PyObject *py_windings(PyObject *self, PyObject *args)
{
    PyObject *obj;
    if (!PyArg_ParseTuple(args, "O", &obj))
        return NULL;
    Py_buffer view = {0};
    if (PyObject_GetBuffer(obj, &view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0)
        return NULL;
    const char *fmt = view.format ? view.format : "B";
    if ((fmt[0] == '<' || fmt[0] == '=' || fmt[0] == '@') && fmt[1] != '\0')
        fmt++;
    Py_ssize_t f = view.len / (9 * (Py_ssize_t)sizeof(double));
    if (strcmp(fmt, "d") != 0 || view.len != 9 * f * (Py_ssize_t)sizeof(double)) {
        PyBuffer_Release(&view);
        PyErr_SetString(PyExc_ValueError, "triangles: expected a C-contiguous float64 (F, 3, 3) array");
        return NULL;
    }
    const double *tri = (const double *)view.buf;
    for (Py_ssize_t k = 0; k < 9 * f; k++)
        if (!isfinite(tri[k]) || ((k % 3) < 2 && tri[k] < 0)) {
            PyBuffer_Release(&view);
            PyErr_SetString(PyExc_ValueError, "triangles: coordinates must be finite, x and y >= 0");
            return NULL;
        }
    long lo = 0, hi = 0;
    double excess = 0.0;
    int status;
    Py_BEGIN_ALLOW_THREADS
    status = winding(tri, f, &lo, &hi, &excess);
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&view);
    if (status < 0)
        return PyErr_NoMemory();
    return Py_BuildValue("(lld)", lo, hi, excess);
}

static PyMethodDef methods[] = {
    {"windings", py_windings, METH_VARARGS, windings_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_winding",
    "Compiled winding-number range of a closed mesh for segsnake.rasterize.", -1, methods,
};

PyMODINIT_FUNC PyInit__winding(void)
{
    return PyModule_Create(&module);
}
