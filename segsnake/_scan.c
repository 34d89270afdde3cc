/* Scan conversion of closed triangle meshes along the rays at integer (x, y), parallel to z: the
 * inner loops of segsnake.rasterize (masks by the even-odd rule, and winding numbers).
 *
 * Each triangle's projection on (x, y) is scan-converted: a ray belongs to the triangle when it
 * is strictly inside the projection, or on an edge that the top-left rule gives it, the edge
 * function computed from the edge's two vertices in lexicographic order (so the two triangles
 * that share an edge decide a ray on it the same way, to the bit). A crossing is the ray, the
 * height where it meets the triangle, and the sign of the projection's area (+1:
 * counter-clockwise, the face's normal along +z, the ray leaves).
 *
 * - parity: flips a bit per crossing at the first voxel centre at or above it (the mask is the
 *   running XOR along z, taken by the caller). The region stages rasterize the surface every
 *   round, the brain's with 660 000 triangles; numpy's version of this loop took 0.18 s a mask.
 * - windings: the crossings are bucketed by ray, sorted by height within each ray, and the
 *   winding number runs along each ray, the crossings at one height taken together. The region
 *   stages' crossing penalty measures every evaluated surface with it (~10^3 triangles, a few
 *   thousand times a run), where numpy spent ~1 ms in the overhead of some forty small array
 *   operations.
 * - winding_at: the winding number about given points (the faces above each, bucketed by the
 *   unit cells their projections' bounding boxes touch), where the penalty's gradient needs it.
 * - edge_lengths, on_rays: the penalty's mesh gathered from its vertices and faces (its mean
 *   edge, the rays' spacing; its corners in those units, shifted onto the rays), numpy's numbers
 *   to the bit; numpy's gathers and small-axis reductions took 1.5 ms of the 2.5 a 21 x 21
 *   surface's penalty cost.
 *
 * Plain C on Python buffers (no numpy headers); the GIL is released. The arithmetic is the
 * order the comments give, without contraction into fused multiply-adds (setup.py builds with
 * -ffp-contract=off), so every platform decides ties alike.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "_buffers.h"

typedef struct {
    Py_ssize_t ray;
    double z;
    int up;
} Crossing;

/* The edge function of p -> q at (x, y), times `sign`, and whether (x, y) is on the triangle's
 * side of it (ties by the top-left rule: of two triangles that traverse a shared edge in
 * opposite directions exactly one takes a point on it). */
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

/* The sign of the projection of triangle a, b, c on (x, y): +1 counter-clockwise (the face's
 * normal along +z), -1 clockwise, 0 without area (it crosses no ray). */
static double facing(const double *a, const double *b, const double *c)
{
    double area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
    return area > 0 ? 1.0 : (area < 0 ? -1.0 : 0.0);
}

/* Whether the ray at (x, y) meets triangle a, b, c (of projection sign `sign`, not 0), and the
 * height z where it does. */
static int meets(const double *a, const double *b, const double *c, double sign, double x,
                 double y, double *z)
{
    double wa, wb, wc;
    if (!edge(b, c, x, y, sign, &wa) || !edge(c, a, x, y, sign, &wb) ||
        !edge(a, b, x, y, sign, &wc))
        return 0;
    *z = (wa * a[2] + wb * b[2] + wc * c[2]) / (wa + wb + wc);
    return 1;
}

typedef int (*visit_fn)(void *ctx, Py_ssize_t i, Py_ssize_t j, double z, int up);

/* Every crossing of the triangles (f, 3 vertices (x, y, z)) with the rays 0 <= i < nx,
 * 0 <= j < ny, passed to `visit`; stops with its first non-zero return. */
static int scan(const double *tri, Py_ssize_t f, Py_ssize_t nx, Py_ssize_t ny, visit_fn visit,
                void *ctx)
{
    for (Py_ssize_t t = 0; t < f; t++) {
        const double *a = tri + 9 * t, *b = a + 3, *c = a + 6;
        double sign = facing(a, b, c);
        if (sign == 0)
            continue; /* a projection without area crosses no ray */
        double x0 = ceil(fmin(a[0], fmin(b[0], c[0]))), x1 = floor(fmax(a[0], fmax(b[0], c[0])));
        double y0 = ceil(fmin(a[1], fmin(b[1], c[1]))), y1 = floor(fmax(a[1], fmax(b[1], c[1])));
        if (x1 < 0 || y1 < 0 || x0 > (double)(nx - 1) || y0 > (double)(ny - 1))
            continue; /* misses the grid (and far coordinates are never cast) */
        Py_ssize_t i0 = x0 > 0 ? (Py_ssize_t)x0 : 0, j0 = y0 > 0 ? (Py_ssize_t)y0 : 0;
        Py_ssize_t i1 = x1 < (double)(nx - 1) ? (Py_ssize_t)x1 : nx - 1;
        Py_ssize_t j1 = y1 < (double)(ny - 1) ? (Py_ssize_t)y1 : ny - 1;
        for (Py_ssize_t i = i0; i <= i1; i++)
            for (Py_ssize_t j = j0; j <= j1; j++) {
                double z;
                if (meets(a, b, c, sign, (double)i, (double)j, &z) &&
                    visit(ctx, i, j, z, (int)sign))
                    return -1;
            }
    }
    return 0;
}

typedef struct {
    unsigned char *flips;
    Py_ssize_t ny, nz;
} Parity;

static int flip(void *ctx, Py_ssize_t i, Py_ssize_t j, double z, int up)
{
    Parity *p = ctx;
    double k = ceil(z);
    Py_ssize_t kk = k > 0 ? (k < (double)p->nz ? (Py_ssize_t)k : p->nz) : 0;
    p->flips[(i * p->ny + j) * (p->nz + 1) + kk] ^= 1;
    (void)up;
    return 0;
}

typedef struct {
    Crossing *hits;
    Py_ssize_t n, cap, ny;
} Collect;

static int collect(void *ctx, Py_ssize_t i, Py_ssize_t j, double z, int up)
{
    Collect *c = ctx;
    if (c->n == c->cap) {
        Crossing *more = realloc(c->hits, 2 * c->cap * sizeof(Crossing));
        if (more == NULL)
            return -1;
        c->hits = more;
        c->cap *= 2;
    }
    c->hits[c->n].ray = i * c->ny + j;
    c->hits[c->n].z = z;
    c->hits[c->n].up = up;
    c->n++;
    return 0;
}

static int by_height(const void *a, const void *b)
{
    double za = ((const Crossing *)a)->z, zb = ((const Crossing *)b)->z;
    return (za > zb) - (za < zb);
}

/* 0 on success (lo, hi, excess, box set), -1 when out of memory. `tri`: f triangles of 3
 * vertices (x, y, z), x and y >= 0. `excess`: the summed length, along the rays, of their
 * stretches wound other than 0 or 1 times, each weighted by how far beyond (|w| for w < 0, w - 1
 * for w > 1); `box`: those stretches' bounds (x0, x1, y0, y1, z0, z1), set by the caller to an
 * empty box (+inf, -inf, ...) and left so when there are none. */
static int winding(const double *tri, Py_ssize_t f, long *lo_out, long *hi_out,
                   double *excess_out, double *box)
{
    Py_ssize_t nx = 1, ny = 1;
    for (Py_ssize_t k = 0; k < 3 * f; k++) {
        const double *p = tri + 3 * k;
        if (p[0] + 1 > nx)
            nx = (Py_ssize_t)floor(p[0]) + 1;
        if (p[1] + 1 > ny)
            ny = (Py_ssize_t)floor(p[1]) + 1;
    }
    Collect col = {malloc((4 * f + 16) * sizeof(Crossing)), 0, 4 * f + 16, ny};
    if (col.hits == NULL || scan(tri, f, nx, ny, collect, &col) < 0) {
        free(col.hits);
        return -1;
    }
    Crossing *hits = col.hits;
    Py_ssize_t n = col.n;
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
            if (beyond && k + 1 < end) {
                excess += (double)beyond * (sorted[k + 1].z - sorted[k].z);
                double x = (double)(r / ny), y = (double)(r % ny);
                box[0] = fmin(box[0], x);
                box[1] = fmax(box[1], x);
                box[2] = fmin(box[2], y);
                box[3] = fmax(box[3], y);
                box[4] = fmin(box[4], sorted[k].z);
                box[5] = fmax(box[5], sorted[k + 1].z);
            }
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

/* The query points' extent along x and along y, in cells, beyond which winding_at refuses them
 * (its bucket grid would not fit in memory). */
#define MAX_CELLS_PER_SIDE 16384.0

/* The winding number of the mesh about each of n points (x, y, z): the signed count of the
 * triangles that the ray from the point up along z crosses (+1 where the face's normal points
 * along the ray, which leaves there), the triangles bucketed by the unit cells of (x, y) that
 * their projections' bounding boxes touch. 0 on success, -1 when out of memory, -2 when the
 * points span more than MAX_CELLS_PER_SIDE cells along x or y. */
static int winding_points(const double *tri, Py_ssize_t f, const double *pts, Py_ssize_t n,
                          long long *out)
{
    if (n == 0)
        return 0;
    double x0 = pts[0], y0 = pts[1], x1 = pts[0], y1 = pts[1];
    for (Py_ssize_t k = 1; k < n; k++) {
        x0 = fmin(x0, pts[3 * k]);
        x1 = fmax(x1, pts[3 * k]);
        y0 = fmin(y0, pts[3 * k + 1]);
        y1 = fmax(y1, pts[3 * k + 1]);
    }
    if (!(x1 - x0 < MAX_CELLS_PER_SIDE) || !(y1 - y0 < MAX_CELLS_PER_SIDE))
        return -2; /* (the caller scales points to about a triangle's size) */
    Py_ssize_t nx = (Py_ssize_t)floor(x1 - x0) + 1, ny = (Py_ssize_t)floor(y1 - y0) + 1;
    Py_ssize_t cells = nx * ny;
    Py_ssize_t *start = calloc(cells + 1, sizeof(Py_ssize_t));
    if (start == NULL)
        return -1;
    /* Two passes over the triangles: count per cell, then fill (a counting sort). */
    Py_ssize_t *list = NULL;
    for (int pass = 0; pass < 2; pass++) {
        for (Py_ssize_t t = 0; t < f; t++) {
            const double *a = tri + 9 * t, *b = a + 3, *c = a + 6;
            double lx = floor(fmin(a[0], fmin(b[0], c[0])) - x0);
            double hx = floor(fmax(a[0], fmax(b[0], c[0])) - x0);
            double ly = floor(fmin(a[1], fmin(b[1], c[1])) - y0);
            double hy = floor(fmax(a[1], fmax(b[1], c[1])) - y0);
            if (hx < 0 || hy < 0 || lx > (double)(nx - 1) || ly > (double)(ny - 1))
                continue;
            Py_ssize_t i0 = lx > 0 ? (Py_ssize_t)lx : 0, j0 = ly > 0 ? (Py_ssize_t)ly : 0;
            Py_ssize_t i1 = hx < (double)(nx - 1) ? (Py_ssize_t)hx : nx - 1;
            Py_ssize_t j1 = hy < (double)(ny - 1) ? (Py_ssize_t)hy : ny - 1;
            for (Py_ssize_t i = i0; i <= i1; i++)
                for (Py_ssize_t j = j0; j <= j1; j++) {
                    if (pass == 0)
                        start[i * ny + j + 1]++;
                    else
                        list[start[i * ny + j]++] = t;
                }
        }
        if (pass == 0) {
            for (Py_ssize_t r = 0; r < cells; r++)
                start[r + 1] += start[r];
            list = malloc((start[cells] ? start[cells] : 1) * sizeof(Py_ssize_t));
            if (list == NULL) {
                free(start);
                return -1;
            }
        }
    }
    /* Filling advanced start[r] to the end of cell r's list: one cell back, start[r] is its
     * beginning and start[r + 1] its end. */
    memmove(start + 1, start, cells * sizeof(Py_ssize_t));
    start[0] = 0;
    for (Py_ssize_t k = 0; k < n; k++) {
        const double *p = pts + 3 * k;
        Py_ssize_t cell = (Py_ssize_t)floor(p[0] - x0) * ny + (Py_ssize_t)floor(p[1] - y0);
        long long w = 0;
        for (Py_ssize_t e = start[cell]; e < start[cell + 1]; e++) {
            const double *a = tri + 9 * list[e], *b = a + 3, *c = a + 6;
            double sign = facing(a, b, c), z;
            if (sign != 0 && meets(a, b, c, sign, p[0], p[1], &z) && z > p[2])
                w += (long long)sign;
        }
        out[k] = w;
    }
    free(start);
    free(list);
    return 0;
}

/* The triangles' buffer: a C-contiguous float64 (F, 3, 3) array of finite coordinates. */
static int get_triangles(PyObject *obj, Py_buffer *view, Py_ssize_t *f)
{
    if (PyObject_GetBuffer(obj, view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0)
        return -1;
    *f = view->len / (9 * (Py_ssize_t)sizeof(double));
    if (!is_float64(view) || view->len != 9 * *f * (Py_ssize_t)sizeof(double)) {
        PyBuffer_Release(view);
        PyErr_SetString(PyExc_ValueError, "triangles: expected a C-contiguous float64 (F, 3, 3) array");
        return -1;
    }
    const double *tri = (const double *)view->buf;
    for (Py_ssize_t k = 0; k < 9 * *f; k++)
        if (!isfinite(tri[k])) {
            PyBuffer_Release(view);
            PyErr_SetString(PyExc_ValueError, "triangles: coordinates must be finite");
            return -1;
        }
    return 0;
}

PyDoc_STRVAR(windings_doc,
"windings(triangles) -> (lo, hi, excess, box)\n\n"
"The least and greatest winding number (0 counted) of a closed mesh about the rays at integer\n"
"(x, y), the summed length of the rays' stretches wound beyond 0 or 1, times how far beyond, and\n"
"those stretches' bounds (x0, x1, y0, y1, z0, z1) (+-inf when there are none): triangles is a\n"
"C-contiguous float64 array (F, 3, 3) of vertex coordinates, x, y >= 0.");

static PyObject *py_windings(PyObject *self, PyObject *args)
{
    PyObject *obj;
    if (!PyArg_ParseTuple(args, "O", &obj))
        return NULL;
    Py_buffer view = {0};
    Py_ssize_t f;
    if (get_triangles(obj, &view, &f) < 0)
        return NULL;
    const double *tri = (const double *)view.buf;
    for (Py_ssize_t k = 0; k < 9 * f; k++)
        if ((k % 3) < 2 && tri[k] < 0) {
            PyBuffer_Release(&view);
            PyErr_SetString(PyExc_ValueError, "triangles: x and y must be >= 0");
            return NULL;
        }
    long lo = 0, hi = 0;
    double excess = 0.0;
    double box[6] = {INFINITY, -INFINITY, INFINITY, -INFINITY, INFINITY, -INFINITY};
    int status;
    Py_BEGIN_ALLOW_THREADS
    status = winding(tri, f, &lo, &hi, &excess, box);
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&view);
    if (status < 0)
        return PyErr_NoMemory();
    return Py_BuildValue("(lld(dddddd))", lo, hi, excess, box[0], box[1], box[2], box[3], box[4],
                         box[5]);
}

PyDoc_STRVAR(winding_at_doc,
"winding_at(triangles, points, out)\n\n"
"The winding number of a closed, consistently oriented mesh (a C-contiguous float64 array\n"
"(F, 3, 3) of vertex coordinates) about each point of a C-contiguous float64 array (N, 3), into\n"
"the C-contiguous int64 array out (N,): the signed count of the faces above the point along z\n"
"(+1 for a face whose normal points up). Coordinates in units of about a triangle's size.");

static PyObject *py_winding_at(PyObject *self, PyObject *args)
{
    PyObject *obj, *pts_obj, *out_obj;
    if (!PyArg_ParseTuple(args, "OOO", &obj, &pts_obj, &out_obj))
        return NULL;
    Py_buffer view = {0}, pts = {0}, out = {0};
    Py_ssize_t f;
    if (get_triangles(obj, &view, &f) < 0)
        return NULL;
    if (PyObject_GetBuffer(pts_obj, &pts, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) {
        PyBuffer_Release(&view);
        return NULL;
    }
    if (PyObject_GetBuffer(out_obj, &out, PyBUF_C_CONTIGUOUS | PyBUF_WRITABLE | PyBUF_FORMAT) < 0) {
        PyBuffer_Release(&view);
        PyBuffer_Release(&pts);
        return NULL;
    }
    Py_ssize_t n = pts.len / (3 * (Py_ssize_t)sizeof(double));
    int ok = is_float64(&pts) && pts.len == 3 * n * (Py_ssize_t)sizeof(double) &&
             is_int64(&out) && out.len == n * (Py_ssize_t)sizeof(long long);
    const double *p = (const double *)pts.buf;
    for (Py_ssize_t k = 0; ok && k < 3 * n; k++)
        ok = isfinite(p[k]);
    if (!ok) {
        PyBuffer_Release(&view);
        PyBuffer_Release(&pts);
        PyBuffer_Release(&out);
        PyErr_SetString(PyExc_ValueError,
                        "points: expected finite float64 (N, 3) and out int64 (N,), C-contiguous");
        return NULL;
    }
    int status;
    Py_BEGIN_ALLOW_THREADS
    status = winding_points((const double *)view.buf, f, p, n, (long long *)out.buf);
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&view);
    PyBuffer_Release(&pts);
    PyBuffer_Release(&out);
    if (status == -2) {
        PyErr_SetString(PyExc_ValueError, "points: spread over too many cells along x or y");
        return NULL;
    }
    if (status < 0)
        return PyErr_NoMemory();
    Py_RETURN_NONE;
}

PyDoc_STRVAR(parity_doc,
"parity(triangles, flips)\n\n"
"For each crossing of the rays 0 <= i < nx, 0 <= j < ny with a triangle (a C-contiguous float64\n"
"array (F, 3, 3) of vertex coordinates), flip the bit flips[i, j, k], k the first integer at or\n"
"above the crossing's height clipped to [0, nz]: flips is a C-contiguous uint8 array\n"
"(nx, ny, nz + 1), whose running XOR along its last axis is then the even-odd mask.");

static PyObject *py_parity(PyObject *self, PyObject *args)
{
    PyObject *obj, *flips_obj;
    Py_ssize_t nx, ny, nz;
    if (!PyArg_ParseTuple(args, "O(nnn)O", &obj, &nx, &ny, &nz, &flips_obj))
        return NULL;
    if (nx < 1 || ny < 1 || nz < 0) {
        PyErr_SetString(PyExc_ValueError, "the grid must have at least one ray");
        return NULL;
    }
    Py_buffer view = {0}, out = {0};
    Py_ssize_t f;
    if (get_triangles(obj, &view, &f) < 0)
        return NULL;
    if (PyObject_GetBuffer(flips_obj, &out, PyBUF_C_CONTIGUOUS | PyBUF_WRITABLE) < 0) {
        PyBuffer_Release(&view);
        return NULL;
    }
    if (out.itemsize != 1 || out.len / nx / ny != nz + 1 || out.len != nx * ny * (nz + 1)) {
        PyBuffer_Release(&view);
        PyBuffer_Release(&out);
        PyErr_SetString(PyExc_ValueError, "flips: expected a C-contiguous uint8 array (nx, ny, nz + 1)");
        return NULL;
    }
    Parity par = {(unsigned char *)out.buf, ny, nz};
    Py_BEGIN_ALLOW_THREADS
    scan((const double *)view.buf, f, nx, ny, flip, &par);
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&view);
    PyBuffer_Release(&out);
    Py_RETURN_NONE;
}

/* The mesh: vertices, a C-contiguous float64 (n, 3) array of finite coordinates, and faces, a
 * C-contiguous int64 (F, 3) array (its indices are checked where they are read: another thread
 * may write the array while the GIL is released); and `out`, a C-contiguous writable float64
 * array of `per_face` values a face that shares no memory with either. 0, or -1 with an
 * exception set and nothing held. */
static int get_mesh(PyObject *pts_obj, PyObject *faces_obj, PyObject *out_obj, Py_ssize_t per_face,
                    Py_buffer *pts, Py_buffer *faces, Py_buffer *out, Py_ssize_t *n, Py_ssize_t *f)
{
    if (PyObject_GetBuffer(pts_obj, pts, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0)
        return -1;
    if (PyObject_GetBuffer(faces_obj, faces, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) {
        PyBuffer_Release(pts);
        return -1;
    }
    if (PyObject_GetBuffer(out_obj, out, PyBUF_C_CONTIGUOUS | PyBUF_WRITABLE | PyBUF_FORMAT) < 0) {
        PyBuffer_Release(pts);
        PyBuffer_Release(faces);
        return -1;
    }
    *n = pts->len / (3 * (Py_ssize_t)sizeof(double));
    *f = faces->len / (3 * (Py_ssize_t)sizeof(long long));
    const char *error = NULL;
    const double *p = (const double *)pts->buf;
    if (!is_float64(pts) || pts->len != 3 * *n * (Py_ssize_t)sizeof(double))
        error = "points: expected a C-contiguous float64 (n, 3) array";
    for (Py_ssize_t k = 0; !error && k < 3 * *n; k++)
        if (!isfinite(p[k]))
            error = "points: coordinates must be finite";
    if (!error && (!is_int64(faces) || faces->len != 3 * *f * (Py_ssize_t)sizeof(long long)))
        error = "faces: expected a C-contiguous int64 (F, 3) array";
    if (!error && (!is_float64(out) || out->len != per_face * *f * (Py_ssize_t)sizeof(double)))
        error = per_face == 3 ? "out: expected a C-contiguous float64 (F, 3) array"
                              : "out: expected a C-contiguous float64 (F, 3, 3) array";
    if (!error && (overlap(out, pts) || overlap(out, faces)))
        error = "out: shares memory with points or faces";
    if (error) {
        PyBuffer_Release(pts);
        PyBuffer_Release(faces);
        PyBuffer_Release(out);
        PyErr_SetString(PyExc_ValueError, error);
        return -1;
    }
    return 0;
}

/* Releases get_mesh's buffers: 0, or -1 with an exception set when a face index was bad. */
static int mesh_done(Py_buffer *pts, Py_buffer *faces, Py_buffer *out, int bad_index)
{
    PyBuffer_Release(pts);
    PyBuffer_Release(faces);
    PyBuffer_Release(out);
    if (bad_index) {
        PyErr_SetString(PyExc_ValueError, "faces: vertex indices must lie in [0, n)");
        return -1;
    }
    return 0;
}

PyDoc_STRVAR(edge_lengths_doc,
"edge_lengths(points, faces, out)\n\n"
"The length of each face's edges into the C-contiguous float64 array out (F, 3): out[t, i] =\n"
"|points[faces[t, i]] - points[faces[t, i - 1]]| (i - 1 taken mod 3), the square root of\n"
"dx^2 + dy^2 + dz^2 summed in that order (numpy's norm of the same differences, to the bit).\n"
"points: C-contiguous float64 (n, 3), finite; faces: C-contiguous int64 (F, 3), each in [0, n).");

static PyObject *py_edge_lengths(PyObject *self, PyObject *args)
{
    PyObject *pts_obj, *faces_obj, *out_obj;
    if (!PyArg_ParseTuple(args, "OOO", &pts_obj, &faces_obj, &out_obj))
        return NULL;
    Py_buffer pts = {0}, faces = {0}, out = {0};
    Py_ssize_t n, f;
    if (get_mesh(pts_obj, faces_obj, out_obj, 3, &pts, &faces, &out, &n, &f) < 0)
        return NULL;
    const double *p = (const double *)pts.buf;
    const long long *t = (const long long *)faces.buf;
    double *o = (double *)out.buf;
    int bad = 0;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t k = 0; k < f && !bad; k++)
        for (int i = 0; i < 3; i++) {
            long long ia = t[3 * k + i], ib = t[3 * k + (i + 2) % 3];
            if (ia < 0 || ia >= n || ib < 0 || ib >= n) {
                bad = 1;
                break;
            }
            const double *a = p + 3 * ia, *b = p + 3 * ib;
            double dx = a[0] - b[0], dy = a[1] - b[1], dz = a[2] - b[2];
            o[3 * k + i] = sqrt(dx * dx + dy * dy + dz * dz);
        }
    Py_END_ALLOW_THREADS
    if (mesh_done(&pts, &faces, &out, bad) < 0)
        return NULL;
    Py_RETURN_NONE;
}

PyDoc_STRVAR(on_rays_doc,
"on_rays(points, faces, h, out) -> (ox, oy)\n\n"
"The faces' vertex coordinates in units of h, moved by whole units so that x, y >= 0 (the\n"
"windings kernel's input), into the C-contiguous float64 array out (F, 3, 3): out[t, i] =\n"
"points[faces[t, i]] / h - (ox, oy, 0), (ox, oy) the floor of the least x and y of the faces'\n"
"vertices divided by h ((0, 0) without faces). points: C-contiguous float64 (n, 3), finite;\n"
"faces: C-contiguous int64 (F, 3), each in [0, n); h > 0.");

static PyObject *py_on_rays(PyObject *self, PyObject *args)
{
    PyObject *pts_obj, *faces_obj, *out_obj;
    double h;
    if (!PyArg_ParseTuple(args, "OOdO", &pts_obj, &faces_obj, &h, &out_obj))
        return NULL;
    if (!(h > 0) || !isfinite(h)) {
        PyErr_SetString(PyExc_ValueError, "h: expected a finite number > 0");
        return NULL;
    }
    Py_buffer pts = {0}, faces = {0}, out = {0};
    Py_ssize_t n, f;
    if (get_mesh(pts_obj, faces_obj, out_obj, 9, &pts, &faces, &out, &n, &f) < 0)
        return NULL;
    const double *p = (const double *)pts.buf;
    const long long *t = (const long long *)faces.buf;
    double *o = (double *)out.buf;
    double lo[2] = {0.0, 0.0};
    int bad = 0;
    Py_BEGIN_ALLOW_THREADS
    /* the scaled corners first, then the shift of their least x and y (each value exactly
     * numpy's corners / h - floor(min)) */
    if (f > 0)
        lo[0] = lo[1] = INFINITY;
    for (Py_ssize_t k = 0; k < 3 * f; k++) {
        if (t[k] < 0 || t[k] >= n) {
            bad = 1;
            break;
        }
        const double *a = p + 3 * t[k];
        for (int d = 0; d < 3; d++)
            o[3 * k + d] = a[d] / h;
        if (o[3 * k] < lo[0])
            lo[0] = o[3 * k];
        if (o[3 * k + 1] < lo[1])
            lo[1] = o[3 * k + 1];
    }
    if (!bad) {
        lo[0] = floor(lo[0]);
        lo[1] = floor(lo[1]);
        for (Py_ssize_t k = 0; k < 3 * f; k++) {
            o[3 * k] -= lo[0];
            o[3 * k + 1] -= lo[1];
        }
    }
    Py_END_ALLOW_THREADS
    if (mesh_done(&pts, &faces, &out, bad) < 0)
        return NULL;
    return Py_BuildValue("(dd)", lo[0], lo[1]);
}

static PyMethodDef methods[] = {
    {"windings", py_windings, METH_VARARGS, windings_doc},
    {"parity", py_parity, METH_VARARGS, parity_doc},
    {"winding_at", py_winding_at, METH_VARARGS, winding_at_doc},
    {"edge_lengths", py_edge_lengths, METH_VARARGS, edge_lengths_doc},
    {"on_rays", py_on_rays, METH_VARARGS, on_rays_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_scan",
    "Compiled scan conversion of closed meshes along rays (masks and winding numbers) for "
    "segsnake.rasterize.", -1, methods,
};

PyMODINIT_FUNC PyInit__scan(void)
{
    return PyModule_Create(&module);
}
