/* The flux integrand and its derivatives on a quadrature grid: the per-node arithmetic of
 * segsnake.energy.flux_integrand_grads.
 *
 * numpy's version builds about ten temporaries of the grid's size for what is a dozen products
 * a node (0.20 ms of a 1.2 ms energy evaluation at 12 960 nodes). Here one pass over the nodes
 * writes each output once. The operations are numpy's, in its order (and setup.py builds with
 * -ffp-contract=off, so no product is fused into a sum): the outputs are the same to the bit.
 * The sum of the terms is left to numpy (its pairwise order).
 *
 * Plain C on Python buffers (no numpy headers; C-contiguous float64 buffers).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "_buffers.h"

/* For node i (x, y, z the components of its 3-vectors):
 *   nx = o (sv_y su_z - sv_z su_y)          the outward normal's x component
 *   term = (W G) nx                         its share of sum W G n_x
 *   g_sigma = (W nx) dG                     d/d sigma
 *   g_u = (0, -(W G o) sv_z, (W G o) sv_y)  d/d sigma_u
 *   g_v = (0, (W G o) su_z, -(W G o) su_y)  d/d sigma_v */
static void integrand(const double *G, const double *dG, const double *su, const double *sv,
                      const double *W, double o, Py_ssize_t n, double *term, double *g_sigma,
                      double *g_u, double *g_v)
{
    for (Py_ssize_t i = 0; i < n; i++) {
        const double *a = su + 3 * i, *b = sv + 3 * i, *d = dG + 3 * i;
        double nx = o * (b[1] * a[2] - b[2] * a[1]);
        double wg = W[i] * G[i];
        double wn = W[i] * nx;
        double wgo = wg * o;
        term[i] = wg * nx;
        g_sigma[3 * i] = wn * d[0];
        g_sigma[3 * i + 1] = wn * d[1];
        g_sigma[3 * i + 2] = wn * d[2];
        g_u[3 * i] = 0.0;
        g_u[3 * i + 1] = -wgo * b[2];
        g_u[3 * i + 2] = wgo * b[1];
        g_v[3 * i] = 0.0;
        g_v[3 * i + 1] = wgo * a[2];
        g_v[3 * i + 2] = -wgo * a[1];
    }
}

PyDoc_STRVAR(integrand_doc,
"integrand(G, dG, su, sv, weights, orientation, term_out, g_sigma_out, g_u_out, g_v_out)\n\n"
"Fill term_out (N,) with W G n_x and g_sigma_out, g_u_out, g_v_out (N, 3) with its derivatives\n"
"with respect to sigma, sigma_u and sigma_v, from G (N,), dG, su, sv (N, 3) and weights (N,).\n"
"All arrays C-contiguous float64; the outputs may not overlap each other or an input.");

static PyObject *py_integrand(PyObject *self, PyObject *args)
{
    PyObject *obj[10];
    double o;
    if (!PyArg_ParseTuple(args, "OOOOOdOOOO", &obj[0], &obj[1], &obj[2], &obj[3], &obj[4], &o,
                          &obj[6], &obj[7], &obj[8], &obj[9]))
        return NULL;
    obj[5] = NULL;
    static const char *names[10] = {"G", "dG", "su", "sv", "weights", NULL,
                                    "term_out", "g_sigma_out", "g_u_out", "g_v_out"};
    static const int width[10] = {1, 3, 3, 3, 1, 0, 1, 3, 3, 3};
    Py_buffer v[10];
    memset(v, 0, sizeof(v));
    PyObject *result = NULL;
    Py_buffer first = {0};
    if (PyObject_GetBuffer(obj[0], &first, PyBUF_SIMPLE) < 0)
        return NULL;
    Py_ssize_t n = first.len / (Py_ssize_t)sizeof(double);
    PyBuffer_Release(&first);
    for (int k = 0; k < 10; k++) {
        if (k == 5)
            continue;
        if (get_doubles(obj[k], &v[k], k > 5, width[k] * n, names[k]) < 0)
            goto done;
    }
    for (int k = 6; k < 10; k++)
        for (int j = 0; j < 10; j++)
            if (j != 5 && j != k && overlap(&v[k], &v[j])) {
                PyErr_Format(PyExc_ValueError, "%s overlaps %s", names[k], names[j]);
                goto done;
            }
    Py_BEGIN_ALLOW_THREADS
    integrand((const double *)v[0].buf, (const double *)v[1].buf, (const double *)v[2].buf,
              (const double *)v[3].buf, (const double *)v[4].buf, o, n, (double *)v[6].buf,
              (double *)v[7].buf, (double *)v[8].buf, (double *)v[9].buf);
    Py_END_ALLOW_THREADS
    result = Py_None;
    Py_INCREF(result);
done:
    /* A view that was never filled has obj == NULL; PyBuffer_Release ignores it. */
    for (int k = 0; k < 10; k++)
        PyBuffer_Release(&v[k]);
    return result;
}

static PyMethodDef methods[] = {
    {"integrand", py_integrand, METH_VARARGS, integrand_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_flux",
    "Compiled flux integrand and its derivatives for segsnake.energy.", -1, methods,
};

PyMODINIT_FUNC PyInit__flux(void)
{
    return PyModule_Create(&module);
}
