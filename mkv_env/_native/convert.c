/* _native/convert.c: conversions between Python objects and C arrays.
 *
 * Owns: the WheelState attribute names and load_state/store_state, get_constants (the K
 * buffer), get_doubles (a float64 buffer of known length), get_pointers (function addresses),
 * tuple_of/append_tuple/tuples_of (float tuples out), tuple_doubles (float tuples in).
 * Relies on: Python.h, kernel.h (K_LEN, S_LEN). */

static const char *STATE_NAMES[S_LEN] = {
    "drive_omega", "steer", "steer_rate", "drive_angle", "roller_angle", "drive_budget",
    "drive_current", "steer_current"};
static PyObject *state_names[S_LEN];

static int load_state(PyObject *obj, double *st)
{
    for (int i = 0; i < S_LEN; i++) {
        PyObject *v = PyObject_GetAttr(obj, state_names[i]);
        if (v == NULL)
            return -1;
        st[i] = PyFloat_AsDouble(v);
        Py_DECREF(v);
        if (st[i] == -1.0 && PyErr_Occurred())
            return -1;
    }
    return 0;
}

static int store_state(PyObject *obj, const double *st)
{
    for (int i = 0; i < S_LEN; i++) {
        PyObject *v = PyFloat_FromDouble(st[i]);
        if (v == NULL)
            return -1;
        int rc = PyObject_SetAttr(obj, state_names[i], v);
        Py_DECREF(v);
        if (rc < 0)
            return -1;
    }
    return 0;
}

static int get_constants(PyObject *obj, Py_buffer *view)
{
    if (PyObject_GetBuffer(obj, view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0)
        return -1;
    if (view->itemsize != sizeof(double) || view->len != (Py_ssize_t)(K_LEN * sizeof(double)) ||
        view->format == NULL || strcmp(view->format, "d") != 0) {
        PyBuffer_Release(view);
        PyErr_Format(PyExc_ValueError, "constants must be %d float64 values", K_LEN);
        return -1;
    }
    return 0;
}

static int get_doubles(PyObject *obj, double *dst, Py_ssize_t want, const char *what)
{
    Py_buffer v;
    if (PyObject_GetBuffer(obj, &v, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0)
        return -1;
    int ok = v.itemsize == sizeof(double) && v.format && strcmp(v.format, "d") == 0 &&
             v.len == want * (Py_ssize_t)sizeof(double);
    if (ok)
        memcpy(dst, v.buf, (size_t)v.len);
    PyBuffer_Release(&v);
    if (!ok) {
        PyErr_Format(PyExc_ValueError, "%s must be %zd float64 values", what, want);
        return -1;
    }
    return 0;
}

/* Function addresses (ints) from ``args`` into ``out``; -1 with a Python error set. */
static int get_pointers(PyObject *const *args, int n, void **out)
{
    for (int i = 0; i < n; i++) {
        out[i] = PyLong_AsVoidPtr(args[i]);
        if (out[i] == NULL) {
            if (!PyErr_Occurred())
                PyErr_SetString(PyExc_ValueError, "null function pointer");
            return -1;
        }
    }
    return 0;
}

static PyObject *tuple_of(const double *v, int n)
{
    PyObject *t = PyTuple_New(n);
    if (t == NULL)
        return NULL;
    for (int i = 0; i < n; i++) {
        PyObject *f = PyFloat_FromDouble(v[i]);
        if (f == NULL) {
            Py_DECREF(t);
            return NULL;
        }
        PyTuple_SET_ITEM(t, i, f);
    }
    return t;
}

static int append_tuple(PyObject *list, const double *v, int n)
{
    PyObject *t = tuple_of(v, n);
    if (t == NULL)
        return -1;
    int rc = PyList_Append(list, t);
    Py_DECREF(t);
    return rc;
}

/* A list of n tuples of w floats. */
static PyObject *tuples_of(const double *v, long n, int w)
{
    PyObject *out = PyList_New(0);
    if (out == NULL)
        return NULL;
    for (long k = 0; k < n; k++)
        if (append_tuple(out, v + (size_t)w * (size_t)k, w) < 0) {
            Py_DECREF(out);
            return NULL;
        }
    return out;
}

static int tuple_doubles(PyObject *t, double *out, int n)
{
    PyObject *f = PySequence_Fast(t, "an obstacle must be a sequence of numbers");
    if (f == NULL)
        return -1;
    if (PySequence_Fast_GET_SIZE(f) != n) {
        Py_DECREF(f);
        PyErr_Format(PyExc_ValueError, "an obstacle needs %d numbers", n);
        return -1;
    }
    for (int i = 0; i < n; i++)
        out[i] = PyFloat_AsDouble(PySequence_Fast_GET_ITEM(f, i));
    Py_DECREF(f);
    return PyErr_Occurred() ? -1 : 0;
}
