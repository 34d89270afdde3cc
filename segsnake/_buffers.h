/* The checks segsnake's compiled kernels (_sampling.c, _scan.c, _flux.c, _distance.c) make of
 * the Python buffers they are given: the struct format without its byte-order prefix, float64 /
 * int64 element types, a C-contiguous buffer of an exact size, and outputs that share no memory
 * with what is read. Included by each kernel (static inline: each keeps what it uses). */
#ifndef SEGSNAKE_BUFFERS_H
#define SEGSNAKE_BUFFERS_H

#include <Python.h>  /* (after the kernel's own PY_SSIZE_T_CLEAN and Python.h) */
#include <string.h>

/* A buffer's struct format without its byte-order prefix ("d": float64, "q": int64). */
static inline const char *bare_format(const Py_buffer *view)
{
    const char *fmt = view->format ? view->format : "B";
    if ((fmt[0] == '<' || fmt[0] == '=' || fmt[0] == '@') && fmt[1] != '\0')
        fmt++;
    return fmt;
}

static inline int is_float64(const Py_buffer *view)
{
    return strcmp(bare_format(view), "d") == 0 && view->itemsize == sizeof(double);
}

static inline int is_int64(const Py_buffer *view)
{
    const char *fmt = bare_format(view);
    return (strcmp(fmt, "q") == 0 || (strcmp(fmt, "l") == 0 && sizeof(long) == 8)) &&
           view->itemsize == sizeof(long long);
}

/* Do two buffers share memory? (an output over an input would be overwritten while read) */
static inline int overlap(const Py_buffer *a, const Py_buffer *b)
{
    const char *a0 = (const char *)a->buf, *b0 = (const char *)b->buf;
    return a->len > 0 && b->len > 0 && a0 < b0 + b->len && b0 < a0 + a->len;
}

/* A C-contiguous buffer of exactly `count` values (any count when negative) of format `want`
 * ("d": float64, "f": float32; PyBUF_FORMAT: an int64 array of the same size is refused, not
 * read as doubles), writable when asked. 0 on success, -1 with an exception set. */
static inline int get_values(PyObject *obj, Py_buffer *view, int writable, Py_ssize_t count,
                             const char *want, const char *name)
{
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, view, flags) < 0)
        return -1;
    Py_ssize_t item = want[0] == 'd' ? (Py_ssize_t)sizeof(double) : (Py_ssize_t)sizeof(float);
    if (strcmp(bare_format(view), want) != 0 || view->itemsize != item ||
        (count >= 0 && view->len != count * item)) {
        PyErr_Format(PyExc_ValueError, "%s: expected a C-contiguous %s array of %zd values",
                     name, want[0] == 'd' ? "float64" : "float32", count);
        PyBuffer_Release(view);
        return -1;
    }
    return 0;
}

static inline int get_doubles(PyObject *obj, Py_buffer *view, int writable, Py_ssize_t count,
                              const char *name)
{
    return get_values(obj, view, writable, count, "d", name);
}

#endif
