/* mkv_env._fastsim: the MK-V's wheel/motor substep loop (mkv_env.robot.Robot.advance) in C.
 *
 * The same arithmetic as the Python loop in robot.py, operation for operation and in the same
 * order, so the two give the same bits: IEEE doubles, no FMA contraction (-ffp-contract=off),
 * libm's cos/sin called one by one (-fno-builtin-sin/-cos: no sincos merging), and Python's own
 * math.hypot (CPython's vector_norm, not libm's hypot) called back for the rare sliding branch.
 * Chipmunk is reached through function pointers taken from pymunk's cffi module (bind()), so
 * this module links against nothing but libm.
 *
 * State in and out: the WheelState object's attributes (drive_omega, steer, steer_rate,
 * drive_angle, roller_angle, drive_budget, drive_current, steer_current).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>

typedef struct { double x, y; } cpVect;
typedef cpVect (*get_vect_fn)(const void *);
typedef double (*get_double_fn)(const void *);
typedef void (*set_vect_fn)(void *, cpVect);
typedef void (*set_double_fn)(void *, double);
typedef void (*step_fn)(void *, double);

static get_vect_fn cp_get_v = NULL;
static get_double_fn cp_get_w = NULL, cp_get_a = NULL;
static set_vect_fn cp_set_f = NULL;
static set_double_fn cp_set_t = NULL;
static step_fn cp_step = NULL;
static PyObject *py_hypot = NULL;

/* Layout of the constants vector K (see Robot._kernel_constants). */
enum {
    K_XD, K_XS, K_RW, K_INV_RS, K_LIM, K_IM, K_II, K_TIRE_MU, K_N_DRIVE, K_N_STEER,
    K_S_V, K_S_K, K_S_R, K_S_J, K_S_C, K_FRIC, K_D_V, K_D_K, K_D_R, K_D_J, K_D_C,
    K_MASS, K_MOMENT, K_LEN
};
/* Layout of the state vector. */
enum { S_WW, S_DELTA, S_RATE, S_DRIVE_ANGLE, S_ROLLER_ANGLE, S_BUDGET, S_I_DRIVE, S_I_STEER, S_LEN };
static const char *STATE_NAMES[S_LEN] = {
    "drive_omega", "steer", "steer_rate", "drive_angle", "roller_angle", "drive_budget",
    "drive_current", "steer_current"};
static PyObject *state_names[S_LEN];

/* math.hypot(a, b) exactly as the Python loop computes it; sets *err on failure. */
static double call_hypot(double a, double b, int *err)
{
    PyObject *args[2], *r;
    double out;
    args[0] = PyFloat_FromDouble(a);
    args[1] = PyFloat_FromDouble(b);
    if (args[0] == NULL || args[1] == NULL) {
        Py_XDECREF(args[0]);
        Py_XDECREF(args[1]);
        *err = 1;
        return 0.0;
    }
    r = PyObject_Vectorcall(py_hypot, args, 2, NULL);
    Py_DECREF(args[0]);
    Py_DECREF(args[1]);
    if (r == NULL) {
        *err = 1;
        return 0.0;
    }
    out = PyFloat_AsDouble(r);
    Py_DECREF(r);
    return out;
}

/* One robot, n substeps. Returns 0, or -1 with a Python error set. */
static int advance_one(const double *K, void *cpb, void *cpspace, long drive_cmd, long steer_cmd,
                       double dt, long n, double mu_scale, double *st)
{
    const double xd = K[K_XD], xs = K[K_XS], rw = K[K_RW], inv_rs = K[K_INV_RS], lim = K[K_LIM];
    const double im = K[K_IM], iI = K[K_II];
    const double k11 = im + xd * xd * iI;
    const double mu = K[K_TIRE_MU] * mu_scale;
    const double cap_d = mu * K[K_N_DRIVE] * dt;
    const double cap_s = mu * K[K_N_STEER] * dt;
    const double vs = K[K_S_V] * (double)steer_cmd;
    const double s_drive = K[K_S_K] * vs / K[K_S_R];
    const double s_j = K[K_S_J];
    const double s_den = s_j + dt * K[K_S_C];
    const double fric = K[K_FRIC];
    const double s_k_over_r = K[K_S_K] / K[K_S_R];
    const double vs_over_r = vs / K[K_S_R];
    const double vd = K[K_D_V] * (double)drive_cmd;
    const double d_j = K[K_D_J];
    const double jp = d_j + dt * K[K_D_C];
    const double d_push = dt * K[K_D_K] * vd / K[K_D_R];
    const double iJ = 1.0 / jp;
    const double k22 = im + rw * rw * iJ;
    const double d_k_over_r = K[K_D_K] / K[K_D_R];
    const double vd_over_r = vd / K[K_D_R];

    double ww = st[S_WW], delta = st[S_DELTA], rate = st[S_RATE];
    double drive_angle = st[S_DRIVE_ANGLE], roller_angle = st[S_ROLLER_ANGLE];
    double budget = st[S_BUDGET];
    const double jw_over_rw = d_j / rw;
    double cd = cos(delta), sd = sin(delta);
    double k33 = im + cd * cd * xs * xs * iI;
    double k13 = cd * im + xd * cd * xs * iI;
    double k23 = -sd * im;
    int steer_idle = steer_cmd == 0 && rate == 0.0;
    const double m_dt = K[K_MASS] / dt, i_dt = K[K_MOMENT] / dt;
    double ww_seen = ww;
    int err = 0;

    for (long sub = 0; sub < n; sub++) {
        cpVect v = cp_get_v(cpb);
        double vx = v.x, vy = v.y;
        double om = cp_get_w(cpb);
        double th = cp_get_a(cpb);
        double c = cos(th), s = sin(th);
        double u = c * vx + s * vy;
        double w = c * vy - s * vx;
        roller_angle += (cd * u + sd * (w + om * xs)) * dt * inv_rs;
        if (budget > 0.0) {
            double slip = u / rw - ww;
            double cap = budget / jw_over_rw;
            ww += (-cap <= slip && slip <= cap) ? slip : (slip > 0 ? cap : -cap);
        }
        drive_angle += ww * dt;
        ww_seen = ww;

        if (!steer_idle) {
            double torque = s_drive;
            if (rate > 1e-6 || (rate >= -1e-6 && torque > fric))
                torque -= fric;
            else if (rate < -1e-6 || torque < -fric)
                torque += fric;
            else
                torque = 0.0;
            rate = (s_j * rate + dt * torque) / s_den;
            delta += rate * dt;
            if (delta > lim) {
                delta = lim;
                rate = 0.0;
            } else if (delta < -lim) {
                delta = -lim;
                rate = 0.0;
            }
            steer_idle = steer_cmd == 0 && rate == 0.0;
            cd = cos(delta);
            sd = sin(delta);
            k33 = im + cd * cd * xs * xs * iI;
            k13 = cd * im + xd * cd * xs * iI;
            k23 = -sd * im;
        }

        ww = (d_j * ww + d_push) / jp;
        double v1 = w + om * xd;
        double v2 = u - ww * rw;
        double v3 = cd * (w + om * xs) - sd * u;
        double a = k22 * k33 - k23 * k23;
        double det = k11 * a - k13 * k13 * k22;
        double l1 = (-v1 * a + k13 * (v3 * k22 - v2 * k23)) / det;
        double l2 = (k11 * (v3 * k23 - v2 * k33) + k13 * (k13 * v2 - v1 * k23)) / det;
        double l3 = (k11 * (k23 * v2 - k22 * v3) + v1 * k13 * k22) / det;
        double used = l1 * l1 + l2 * l2;
        if (used > cap_d * cap_d || fabs(l3) > cap_s) {
            double a1 = v1, a2 = v2, a3 = v3;
            l1 = l2 = l3 = 0.0;
            for (int it = 0; it < 8; it++) {
                double n1 = l1 - a1 / k11;
                double n2 = l2 - a2 / k22;
                double norm = call_hypot(n1, n2, &err);
                if (err)
                    return -1;
                if (norm > cap_d) {
                    n1 = n1 * cap_d / norm;
                    n2 = n2 * cap_d / norm;
                }
                double d1 = n1 - l1, d2 = n2 - l2;
                l1 = n1;
                l2 = n2;
                a1 += k11 * d1;
                a2 += k22 * d2;
                a3 += k13 * d1 + k23 * d2;
                /* Python: min(max(x, -cap_s), cap_s), first argument kept on ties */
                double x = l3 - a3 / k33;
                double mx = (-cap_s > x) ? -cap_s : x;
                double n3 = (cap_s < mx) ? cap_s : mx;
                double d3 = n3 - l3;
                l3 = n3;
                a1 += k13 * d3;
                a2 += k23 * d3;
            }
            used = l1 * l1 + l2 * l2;
        }
        budget = cap_d - sqrt(used);
        double du = im * (l2 - sd * l3);
        double dw = im * (l1 + cd * l3);
        cpVect f = {(c * du - s * dw) * m_dt, (s * du + c * dw) * m_dt};
        cp_set_f(cpb, f);
        cp_set_t(cpb, (xd * l1 + cd * xs * l3) * iI * i_dt);
        ww -= iJ * rw * l2;
        cp_step(cpspace, dt);
        if (PyErr_Occurred())
            return -1;
    }
    st[S_WW] = ww;
    st[S_DELTA] = delta;
    st[S_RATE] = rate;
    st[S_DRIVE_ANGLE] = drive_angle;
    st[S_ROLLER_ANGLE] = roller_angle;
    st[S_BUDGET] = budget;
    st[S_I_DRIVE] = vd_over_r - d_k_over_r * ww_seen;
    st[S_I_STEER] = vs_over_r - s_k_over_r * rate;
    return 0;
}

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

static int check_bound(void)
{
    if (cp_step == NULL || py_hypot == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "mkv_env._fastsim: bind() has not been called");
        return -1;
    }
    return 0;
}

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
    int rc = advance_one((const double *)kv.buf, body, space, drive, steer, dt, n, mu_scale, st);
    PyBuffer_Release(&kv);
    if (rc < 0 || store_state(args[8], st) < 0)
        return NULL;
    Py_RETURN_NONE;
}

/* advance_many(K, bodies, spaces, drive_cmds, steer_cmds, dt, n, mu_scales, states) -> None
 * bodies/spaces: sequences of pointer ints; drive/steer: sequences of ints; mu_scales: floats;
 * states: sequence of WheelState objects. Robot i is advanced exactly as advance() would. */
static PyObject *fs_advance_many(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer kv;
    if (nargs != 9) {
        PyErr_SetString(PyExc_TypeError, "advance_many() takes 9 arguments");
        return NULL;
    }
    if (check_bound() < 0)
        return NULL;
    double dt = PyFloat_AsDouble(args[5]);
    long n = PyLong_AsLong(args[6]);
    if (PyErr_Occurred())
        return NULL;
    PyObject *seqs[5] = {args[1], args[2], args[3], args[4], args[7]};
    PyObject *fast[6] = {NULL, NULL, NULL, NULL, NULL, NULL};
    PyObject *result = NULL;
    Py_ssize_t count = -1;
    for (int j = 0; j < 6; j++) {
        fast[j] = PySequence_Fast(j < 5 ? seqs[j] : args[8], "advance_many expects sequences");
        if (fast[j] == NULL)
            goto done;
        Py_ssize_t len = PySequence_Fast_GET_SIZE(fast[j]);
        if (count >= 0 && len != count) {
            PyErr_SetString(PyExc_ValueError, "advance_many: sequences of different lengths");
            goto done;
        }
        count = len;
    }
    if (get_constants(args[0], &kv) < 0)
        goto done;
    for (Py_ssize_t i = 0; i < count; i++) {
        double st[S_LEN];
        void *body = PyLong_AsVoidPtr(PySequence_Fast_GET_ITEM(fast[0], i));
        void *space = PyLong_AsVoidPtr(PySequence_Fast_GET_ITEM(fast[1], i));
        long drive = PyLong_AsLong(PySequence_Fast_GET_ITEM(fast[2], i));
        long steer = PyLong_AsLong(PySequence_Fast_GET_ITEM(fast[3], i));
        double mu_scale = PyFloat_AsDouble(PySequence_Fast_GET_ITEM(fast[4], i));
        PyObject *state = PySequence_Fast_GET_ITEM(fast[5], i);
        if (PyErr_Occurred() || load_state(state, st) < 0 ||
            advance_one((const double *)kv.buf, body, space, drive, steer, dt, n, mu_scale,
                        st) < 0 ||
            store_state(state, st) < 0) {
            PyBuffer_Release(&kv);
            goto done;
        }
    }
    PyBuffer_Release(&kv);
    result = Py_None;
    Py_INCREF(result);
done:
    for (int j = 0; j < 6; j++)
        Py_XDECREF(fast[j]);
    return result;
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

/* bind(get_velocity, get_angular_velocity, get_angle, set_force, set_torque, space_step, hypot)
 * The first six are Chipmunk function addresses (ints), the last math.hypot. */
static PyObject *fs_bind(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    void *p[6];
    if (nargs != 7) {
        PyErr_SetString(PyExc_TypeError, "bind() takes 7 arguments");
        return NULL;
    }
    for (int i = 0; i < 6; i++) {
        p[i] = PyLong_AsVoidPtr(args[i]);
        if (p[i] == NULL) {
            if (!PyErr_Occurred())
                PyErr_SetString(PyExc_ValueError, "null function pointer");
            return NULL;
        }
    }
    if (!PyCallable_Check(args[6])) {
        PyErr_SetString(PyExc_TypeError, "hypot must be callable");
        return NULL;
    }
    cp_get_v = (get_vect_fn)p[0];
    cp_get_w = (get_double_fn)p[1];
    cp_get_a = (get_double_fn)p[2];
    cp_set_f = (set_vect_fn)p[3];
    cp_set_t = (set_double_fn)p[4];
    cp_step = (step_fn)p[5];
    Py_XDECREF(py_hypot);
    py_hypot = args[6];
    Py_INCREF(py_hypot);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"bind", (PyCFunction)(void (*)(void))fs_bind, METH_FASTCALL,
     "bind(get_v, get_w, get_a, set_f, set_t, step, hypot): Chipmunk entry points."},
    {"advance", (PyCFunction)(void (*)(void))fs_advance, METH_FASTCALL,
     "advance(K, body, space, drive, steer, dt, n, mu_scale, state): n substeps of one robot."},
    {"advance_many", (PyCFunction)(void (*)(void))fs_advance_many, METH_FASTCALL,
     "advance_many(K, bodies, spaces, drives, steers, dt, n, mu_scales, states): many robots."},
    {"quantize", (PyCFunction)(void (*)(void))fs_quantize, METH_FASTCALL,
     "quantize(truth, inv_q, q, low, high, out): sensor ADC step and clipping into out."},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_fastsim",
                                    "The MK-V substep loop in C (see robot.py).", -1, methods};

PyMODINIT_FUNC PyInit__fastsim(void)
{
    for (int i = 0; i < S_LEN; i++) {
        state_names[i] = PyUnicode_InternFromString(STATE_NAMES[i]);
        if (state_names[i] == NULL)
            return NULL;
    }
    PyObject *m = PyModule_Create(&module);
    if (m == NULL)
        return NULL;
    if (PyModule_AddIntConstant(m, "N_CONSTANTS", K_LEN) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
