/* _native/robot_api.c: the one-robot entry points Python calls outside a Batch.
 *
 * Owns: advance() (Robot.advance), quantize() (SensorSuite.read's ADC step),
 * drive_until_jammed() (MKVJamEnv's start search, mkv_env.envs._drive_until_jammed).
 * Relies on: wheels.c (advance_one, floor_scale), convert.c (load_state, store_state,
 * get_constants, get_doubles), bind.c (check_bound), pyfloat.c (py_hypot). */

/* advance(K, body_ptr, space_ptr, drive_cmd, steer_cmd, dt, n, mu_scale, state) -> None */
static PyObject *fs_advance(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer kv;
    double st[S_LEN];
    if (nargs != 9) {
        PyErr_SetString(PyExc_TypeError, "advance() takes 9 arguments");
        return NULL;
    }
    if (check_bound() < 0)
        return NULL;
    void *body = PyLong_AsVoidPtr(args[1]);
    void *space = PyLong_AsVoidPtr(args[2]);
    long drive = PyLong_AsLong(args[3]);
    long steer = PyLong_AsLong(args[4]);
    double dt = PyFloat_AsDouble(args[5]);
    long n = PyLong_AsLong(args[6]);
    double mu_scale = PyFloat_AsDouble(args[7]);
    if (PyErr_Occurred())
        return NULL;
    if (body == NULL || space == NULL) {
        PyErr_SetString(PyExc_ValueError, "null body or space pointer");
        return NULL;
    }
    if (load_state(args[8], st) < 0)
        return NULL;
    if (get_constants(args[0], &kv) < 0)
        return NULL;
    int rc = advance_one((const double *)kv.buf, body, space, drive, steer, dt, n, mu_scale, st, 0);
    PyBuffer_Release(&kv);
    if (rc < 0 || store_state(args[8], st) < 0)
        return NULL;
    Py_RETURN_NONE;
}

/* quantize(truth, inv_q, q, low, high, out) -> None
 * out[i] = (float)min(max(rint(truth[i] * inv_q[i]) * q[i], low[i]), high[i]): the sensors'
 * ADC step and clipping (mkv_env.sensors.SensorSuite.read), written into the float32 buffer out.
 * Python's round() is round-half-even, as rint() in the default rounding mode; its int result
 * times q equals rint's double times q because the integer is exact in a double (and, being an
 * int, it has no negative zero: -0.3 rounds to 0, so the zero is made positive here too). */
static PyObject *fs_quantize(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer b[5];
    int got = 0;
    PyObject *fast = NULL, *result = NULL;
    if (nargs != 6) {
        PyErr_SetString(PyExc_TypeError, "quantize() takes 6 arguments");
        return NULL;
    }
    fast = PySequence_Fast(args[0], "truth must be a sequence");
    if (fast == NULL)
        return NULL;
    Py_ssize_t n = PySequence_Fast_GET_SIZE(fast);
    for (got = 0; got < 5; got++) {
        int writable = got == 4;
        if (PyObject_GetBuffer(args[got + 1], &b[got],
                               PyBUF_C_CONTIGUOUS | PyBUF_FORMAT |
                                   (writable ? PyBUF_WRITABLE : 0)) < 0)
            goto done;
        Py_ssize_t want = writable ? (Py_ssize_t)sizeof(float) : (Py_ssize_t)sizeof(double);
        const char *fmt = writable ? "f" : "d";
        if (b[got].itemsize != want || b[got].len != n * want || b[got].format == NULL ||
            strcmp(b[got].format, fmt) != 0) {
            got++;
            PyErr_SetString(PyExc_ValueError, "quantize: buffers must be float64 (float32 out) "
                                              "of the truth's length");
            goto done;
        }
    }
    const double *iq = b[0].buf, *q = b[1].buf, *lo = b[2].buf, *hi = b[3].buf;
    float *out = b[4].buf;
    for (Py_ssize_t i = 0; i < n; i++) {
        double x = PyFloat_AsDouble(PySequence_Fast_GET_ITEM(fast, i));
        if (x == -1.0 && PyErr_Occurred())
            goto done;
        double y = x * iq[i];
        if (!isfinite(y)) {
            PyErr_SetString(PyExc_ValueError, "cannot quantize a non-finite sensor value");
            goto done;
        }
        double r = rint(y);
        if (r == 0.0)
            r = 0.0; /* Python's round() returns the int 0: never a negative zero */
        double v = r * q[i];
        double m = (lo[i] > v) ? lo[i] : v;
        out[i] = (float)((hi[i] < m) ? hi[i] : m);
    }
    result = Py_None;
    Py_INCREF(result);
done:
    for (int j = 0; j < got; j++)
        PyBuffer_Release(&b[j]);
    Py_XDECREF(fast);
    return result;
}

/* drive_until_jammed(K, body, space, state, mu_scale, patches, steer, dt, substeps, limit,
 *                    jam_steps, max_steps, counts) -> (jammed, mu_scale)
 * mkv_env.envs._drive_until_jammed after its steering draw, in C: drive forward with the
 * steering command held until the robot has moved less than ``limit`` per period for
 * ``jam_steps`` periods (then jammed = touching an obstacle), at most ``max_steps`` periods.
 * The floor-patch lookup and substeps are World.step's; the wheel state is read from and
 * written back to the WheelState object ``state``. */
static PyObject *fs_drive_until_jammed(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 13) {
        PyErr_SetString(PyExc_TypeError, "drive_until_jammed() takes 13 arguments");
        return NULL;
    }
    double K[K_LEN], st[S_LEN];
    if (get_doubles(args[0], K, K_LEN, "K") < 0 || check_bound() < 0 || cp_get_p == NULL)
        return NULL;
    void *body = PyLong_AsVoidPtr(args[1]), *space = PyLong_AsVoidPtr(args[2]);
    double mu = PyFloat_AsDouble(args[4]);
    long steer = PyLong_AsLong(args[6]);
    double dt = PyFloat_AsDouble(args[7]);
    long substeps = PyLong_AsLong(args[8]);
    double limit = PyFloat_AsDouble(args[9]);
    long jam_steps = PyLong_AsLong(args[10]), max_steps = PyLong_AsLong(args[11]);
    if (PyErr_Occurred())
        return NULL;
    if (body == NULL || space == NULL) {
        PyErr_SetString(PyExc_ValueError, "null body or space pointer");
        return NULL;
    }
    Py_buffer cv;
    if (PyObject_GetBuffer(args[12], &cv, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0)
        return NULL;
    if (cv.itemsize != 8 || cv.len != 40) {
        PyBuffer_Release(&cv);
        PyErr_SetString(PyExc_ValueError, "counts must be int64 x 5");
        return NULL;
    }
    const int64_t *counts = cv.buf;
    PyObject *fast = PySequence_Fast(args[5], "patches must be a sequence");
    if (fast == NULL) {
        PyBuffer_Release(&cv);
        return NULL;
    }
    Py_ssize_t np_ = PySequence_Fast_GET_SIZE(fast);
    double *pt = np_ ? PyMem_Malloc((size_t)np_ * 5 * sizeof(double)) : NULL;
    int jammed = 0;
    PyObject *out = NULL;
    if (np_ && pt == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    for (Py_ssize_t k = 0; k < np_; k++) {
        PyObject *row = PySequence_Fast_GET_ITEM(fast, k);
        if (!PyArg_ParseTuple(row, "ddddd", &pt[5 * k], &pt[5 * k + 1], &pt[5 * k + 2],
                              &pt[5 * k + 3], &pt[5 * k + 4]))
            goto done;
    }
    if (load_state(args[3], st) < 0)
        goto done;
    long run = 0;
    cpVect p0 = cp_get_p(body);
    for (long t = 0; t < max_steps; t++) {
        if (np_)
            mu = floor_scale(K[K_XD], body, pt, np_);
        advance_one(K, body, space, 1, steer, dt, substeps, mu, st, 1);
        cpVect p = cp_get_p(body);
        run = py_hypot(p.x - p0.x, p.y - p0.y) < limit ? run + 1 : 0;
        p0 = p;
        if (run >= jam_steps) {
            jammed = (counts[1] + counts[2] + counts[3] + counts[4]) > 0;
            break;
        }
    }
    if (store_state(args[3], st) < 0)
        goto done;
    out = Py_BuildValue("(Od)", jammed ? Py_True : Py_False, mu);
done:
    PyMem_Free(pt);
    Py_DECREF(fast);
    PyBuffer_Release(&cv);
    return out;
}
