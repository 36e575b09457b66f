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
#include <float.h>
#include <string.h>

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
static PyObject *py_hypot_obj = NULL;

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


/* ---------------------------------------------------------------- CPython's float semantics
 * The kernel's scoring and sensing must give the bits of the Python reference, which uses
 * math.hypot (CPython's vector_norm, not libm's hypot), float % and math.remainder. */
typedef struct { double hi, lo; } dlen;

static inline dlen dl_fast_sum(double a, double b)
{
    double x = a + b;
    double y = (a - x) + b;
    dlen r = {x, y};
    return r;
}

/* Dekker's exact product (CPython 3.11 uses this split; 3.12's fma gives the same exact pair). */
static inline dlen dl_mul(double x, double y)
{
    const double c = 134217729.0; /* 2**27 + 1 */
    double t = c * x, xh = t - (t - x), xl = x - xh;
    t = c * y;
    double yh = t - (t - y), yl = y - yh;
    double z = x * y;
    double zz = (((xh * yh - z) + xh * yl) + xl * yh) + xl * yl;
    dlen r = {z, zz};
    return r;
}

static double vector_norm2(double a, double b, double max)
{
    int max_e;
    frexp(max, &max_e);
    if (max_e < -1023)
        return DBL_MIN * vector_norm2(a / DBL_MIN, b / DBL_MIN, max / DBL_MIN);
    double scale = ldexp(1.0, -max_e);
    double csum = 1.0, frac1 = 0.0, frac2 = 0.0, v[2] = {a, b};
    dlen pr, sm;
    for (int i = 0; i < 2; i++) {
        double x = v[i] * scale;
        pr = dl_mul(x, x);
        sm = dl_fast_sum(csum, pr.hi);
        csum = sm.hi;
        frac1 += pr.lo;
        frac2 += sm.lo;
    }
    double h = sqrt(csum - 1.0 + (frac1 + frac2));
    pr = dl_mul(-h, h);
    sm = dl_fast_sum(csum, pr.hi);
    csum = sm.hi;
    frac1 += pr.lo;
    frac2 += sm.lo;
    double x = csum - 1.0 + (frac1 + frac2);
    h += x / (2.0 * h);
    return h / scale;
}

/* CPython 3.10-3.11's vector_norm for two coordinates: Dekker split, three compensated sums, a
 * differential correction; below DBL_MIN it divides by the largest coordinate. */
static double vector_norm2_v311(double a, double b, double max)
{
    const double T27 = 134217729.0; /* ldexp(1.0, 27) + 1.0 */
    double x, t, hi, lo, h, oldcsum, csum = 1.0, frac1 = 0.0, frac2 = 0.0, frac3 = 0.0;
    double v[2] = {a, b};
    int max_e;
    frexp(max, &max_e);
    if (max_e >= -1023) {
        double scale = ldexp(1.0, -max_e);
        for (int i = 0; i < 2; i++) {
            x = v[i] * scale;
            t = x * T27;
            hi = t - (t - x);
            lo = x - hi;
            x = hi * hi;
            oldcsum = csum;
            csum += x;
            frac1 += (oldcsum - csum) + x;
            x = 2.0 * hi * lo;
            oldcsum = csum;
            csum += x;
            frac2 += (oldcsum - csum) + x;
            frac3 += lo * lo;
        }
        h = sqrt(csum - 1.0 + (frac1 + frac2 + frac3));
        x = h;
        t = x * T27;
        hi = t - (t - x);
        lo = x - hi;
        x = -hi * hi;
        oldcsum = csum;
        csum += x;
        frac1 += (oldcsum - csum) + x;
        x = -2.0 * hi * lo;
        oldcsum = csum;
        csum += x;
        frac2 += (oldcsum - csum) + x;
        x = -lo * lo;
        oldcsum = csum;
        csum += x;
        frac3 += (oldcsum - csum) + x;
        x = csum - 1.0 + (frac1 + frac2 + frac3);
        return (h + x / (2.0 * h)) / scale;
    }
    for (int i = 0; i < 2; i++) {
        x = v[i] / max;
        x = x * x;
        oldcsum = csum;
        csum += x;
        frac1 += (oldcsum - csum) + x;
    }
    return max * sqrt(csum - 1.0 + frac1);
}

/* Which CPython's math.hypot the kernel copies: 0 = 3.10-3.11, 1 = 3.12 and later. Chosen at
 * import by mkv_env.kernel, which checks the choice against this interpreter's math.hypot. */
static int hypot_variant = 0;

/* math.hypot(a, b), bit for bit (Modules/mathmodule.c: math_hypot + vector_norm). */
static double py_hypot(double a, double b)
{
    double x0 = fabs(a), x1 = fabs(b), max = 0.0;
    int nan = 0;
    if (isnan(x0))
        nan = 1;
    else if (x0 > max)
        max = x0;
    if (isnan(x1))
        nan = 1;
    else if (x1 > max)
        max = x1;
    if (isinf(max))
        return max;
    if (nan)
        return NAN;
    if (max == 0.0)
        return max;
    return hypot_variant ? vector_norm2(x0, x1, max) : vector_norm2_v311(x0, x1, max);
}

/* Python's float % (Objects/floatobject.c: float_rem). */
static inline double py_mod(double vx, double wx)
{
    double mod = fmod(vx, wx);
    if (mod) {
        if ((wx < 0) != (mod < 0))
            mod += wx;
    } else {
        mod = copysign(0.0, wx);
    }
    return mod;
}

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
    r = PyObject_Vectorcall(py_hypot_obj, args, 2, NULL);
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
                       double dt, long n, double mu_scale, double *st, int c_hypot)
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
                double norm = c_hypot ? py_hypot(n1, n2) : call_hypot(n1, n2, &err);
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
        if (!c_hypot && PyErr_Occurred())
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
    if (cp_step == NULL || py_hypot_obj == NULL) {
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
    int rc = advance_one((const double *)kv.buf, body, space, drive, steer, dt, n, mu_scale, st, 0);
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
                        st, 0) < 0 ||
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

/* bind(get_velocity, get_angular_velocity, get_angle, set_force, set_torque, space_step, hypot)
 * The first six are Chipmunk function addresses (ints), the last math.hypot. */
static PyObject *fs_bind(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    void *p[6];
    if (nargs != 7) {
        PyErr_SetString(PyExc_TypeError, "bind() takes 7 arguments");
        return NULL;
    }
    if (get_pointers(args, 6, p) < 0)
        return NULL;
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
    Py_XDECREF(py_hypot_obj);
    py_hypot_obj = args[6];
    Py_INCREF(py_hypot_obj);
    Py_RETURN_NONE;
}


/* ============================================================================ the step kernel
 * Batch: N robots' whole control period after the action is decoded (physics, sensors, tracker,
 * reward, termination, info numbers), each robot in a slot of C state, written into numpy
 * buffers registered once. The Python classes in envs.py, sensors.py and tracker.py are the
 * reference: every operation below is theirs, in their order, on the same doubles, so the two
 * give the same bits (tests/mkv_env/test_step_kernel.py). Nothing here calls Python, so a batch
 * steps with the GIL released and, with num_threads > 1, on worker threads (each robot has its
 * own Chipmunk space; a robot's result does not depend on which thread ran it). */

#include <pthread.h>
#include <unistd.h>
#include <sched.h>
#include <stdatomic.h>

/* Sensor noise drawn in C: numpy's own standard normal (libnpyrandom, linked by setup.py when
 * numpy is there at build time) on the env's bit generator, so a slot refills its noise block on
 * whichever thread steps it, with the draws the reference's SensorSuite.draw_block makes.
 * Without it (MKV_NPYRANDOM undefined) Python draws every block (Batch.set_noise). */
#ifdef MKV_NPYRANDOM
#include "numpy/random/distributions.h"
#endif
/* numpy's array API (built with numpy's headers): Batch.collect makes a step's result arrays. */
#ifdef MKV_NUMPY
#define NPY_NO_DEPRECATED_API NPY_1_7_API_VERSION
#include "numpy/arrayobject.h"
#endif

#define NCH 10
#define NOISE_ROWS 256
#define OBSTACLE_TYPE 10

typedef struct { const void *shape; cpVect point; double distance; cpVect gradient; } cpPQInfo;
typedef struct { uintptr_t group; unsigned int categories, mask; } cpFilter;
typedef void *(*pq_fn)(void *, cpVect, double, cpFilter, cpPQInfo *);
typedef void (*arb_shapes_fn)(void *, void **, void **);
typedef uintptr_t (*shape_type_fn)(void *);

static get_vect_fn cp_get_p = NULL;
static pq_fn cp_pq = NULL;
static arb_shapes_fn cp_arb_shapes = NULL;
static shape_type_fn cp_shape_type = NULL;

/* Contact counting as mkv_env.world._on_begin/_on_separate, on the World's int64 counts. */
static void contact_begin(void *arb, void *space, void *data)
{
    int64_t *counts = data;
    void *a, *b;
    cp_arb_shapes(arb, &a, &b);
    uintptr_t ta = cp_shape_type(a);
    uintptr_t t = ta != OBSTACLE_TYPE ? ta : cp_shape_type(b);
    if (t < 5) {
        counts[t] += 1;
        counts[0] += 1;
    }
}

static void contact_separate(void *arb, void *space, void *data)
{
    int64_t *counts = data;
    void *a, *b;
    cp_arb_shapes(arb, &a, &b);
    uintptr_t ta = cp_shape_type(a);
    uintptr_t t = ta != OBSTACLE_TYPE ? ta : cp_shape_type(b);
    if (t < 5)
        counts[t] -= 1;
}

/* Parameters of a batch (the env's constructor arguments), in the order of envs.kernel_params. */
enum {
    P_DT, P_SUBSTEPS, P_PERIOD, P_STUCK_SPEED, P_JAM_STEPS, P_ESC_DIST, P_ESC_FWD, P_FREE_CLEAR,
    P_KIND, P_PROGRESS, P_STUCK_PEN, P_COLL_PEN, P_ESC_REWARD, P_COVERAGE, P_STILL_PEN,
    P_JAM_PEN, P_TIME_PEN, P_SHAPING, P_CELL, P_TICK, P_BATT_V, P_BATT_R, P_LEN
};
enum { KIND_WANDER, KIND_JAM, KIND_WANDER_V1, KIND_JAM_V1 };
/* A slot's doubles: the wheel state (S_*, advance_one's layout) and then the rest. */
enum {
    V_MU = S_LEN, V_TICK_D, V_TICK_R, V_X, V_Y, V_HEAD, V_DIST, V_LAST, V_STUCK_RUN, V_JAMS,
    V_ESCAPES, V_IN_JAM, V_JAM_X, V_JAM_Y, V_COLLS, V_FWD, V_EVENTS, V_PHI, V_LEN
};
/* Output buffers, registered by Batch.outputs(). */
enum {
    O_OBS, O_REW, O_TERM, O_STUCK, O_BUMPED, O_COLL, O_DIST, O_JAMS, O_ESC, O_COLLS, O_IN_JAM,
    O_POSE, O_CELLS, O_ESCAPED, O_LEN
};
static const char O_FMT[O_LEN] = {'f', 'd', '?', '?', '?', '?', 'd', 'q', 'q', 'q', '?', 'd', 'q', '?'};
static const int O_WIDTH[O_LEN] = {NCH, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 3, 1, 1};

enum { ERR_NONE, ERR_NONFINITE, ERR_CELL, ERR_MEMORY, ERR_UNBOUND, ERR_NOPOSE };

typedef struct {
    void *state;
    uint64_t (*next_uint64)(void *st);
    uint32_t (*next_uint32)(void *st);
    double (*next_double)(void *st);
    uint64_t (*next_raw)(void *st);
} np_bitgen;

enum {
    L_MARGIN, L_TRIES, L_BOX0, L_BOX1, L_CYL0, L_CYL1, L_WALL0, L_WALL1, L_ARM0, L_ARM1, L_GAP0,
    L_GAP1, L_DEPTH0, L_DEPTH1, L_CGAP0, L_CGAP1, L_PATCH0, L_PATCH1, L_WALL_R, L_CDF, L_LEN = L_CDF + 5
};

typedef struct { double x, y, r; } circle;

static inline double uni(np_bitgen *g, double a, double b) { return a + (b - a) * g->next_double(g->state); }

static inline void bounding_wall(const double *w, double wall_r, circle *c)
{
    c->x = 0.5 * (w[0] + w[2]);
    c->y = 0.5 * (w[1] + w[3]);
    c->r = 0.5 * py_hypot(w[2] - w[0], w[3] - w[1]) + wall_r;
}

/* math.hypot(dx, dy) < R, as Python computes it, but hypot only where it could matter: the
 * squared distance (relative error < 1e-15) decides when it is more than 1e-9 away from R^2. */
static inline int near(double dx, double dy, double R)
{
    double d2 = dx * dx + dy * dy, R2 = R * R;
    if (isfinite(d2) && isfinite(R2) && R > 0.0 && d2 > 1e-200 && R2 > 1e-200) {
        if (d2 < R2 * (1.0 - 1e-9))
            return 1;
        if (d2 > R2 * (1.0 + 1e-9))
            return 0;
    }
    return py_hypot(dx, dy) < R;
}

typedef struct {
    void *body, *space;
    int64_t *contacts;
    double *patches;
    Py_ssize_t npatch;
    double v[V_LEN];
    double noise[NOISE_ROWS * NCH];
    long row;
    uint64_t *cells;
    int64_t ncells, cap;
    int err;
    PyObject *keep; /* the World's counts array: kept alive while bound */
    void *gen;      /* the episode's numpy bitgen_t (noise drawn in C), or NULL */
    PyObject *gen_keep; /* its BitGenerator: kept alive while bound */
    double nstd[NCH], nbias[NCH];
    /* The world the kernel built itself at the slot's last reset (reset_slot), until Python
     * adopts it (Batch.adopt): while cworld is 1 the space, bodies and shapes are the slot's. */
    int cworld;
    void *sbody;          /* its static body */
    void *rshapes[4];     /* the robot's shapes */
    void **sshapes;       /* the obstacles' shapes */
    Py_ssize_t nsshapes, sscap;
    double *lay;          /* its layout: walls (4 numbers each), boxes (5), cylinders (3) */
    long nwall, nbox, ncyl;
    size_t laycap;
    int64_t own_counts[5]; /* its contact counts (World.contacts once adopted) */
    double start[3];      /* its start pose */
    PyObject *retired;    /* a Python world's counts array a reset let go (released under the GIL) */
} Slot;

/* A reset's constants (Batch.set_reset, from mkv_env.kernel.reset_constants): the arena, the
 * obstacles, the space, the start-pose search and the robot's body and shapes. */
enum {
    R_W, R_H, R_NCLUTTER, R_NPATCH, R_PSCALE, R_WALL_R, R_OBS_FRIC, R_OBS_ELAST, R_OBS_TYPE,
    R_ITER, R_DAMP, R_MARGIN, R_CLEAR, R_TRIES, R_ATTEMPTS, R_MASS, R_MOMENT, R_FRIC,
    R_TYPES, R_CHASSIS = R_TYPES + 4, R_FL = R_CHASSIS + 8, R_FR = R_FL + 4, R_RB = R_FR + 4,
    R_BUMP_R = R_RB + 4, R_GROUP, R_H_BEGIN, R_H_SEP, R_H_DATA, R_LEN
};

typedef struct BatchObject BatchObject;

typedef struct {
    _Alignas(64) atomic_long next; /* the next robot of this group to claim (own cache line) */
    BatchObject *b;
    int group;
    pthread_t th;
} Worker;

struct BatchObject {
    PyObject_HEAD
    Py_ssize_t n;
    Slot *slots;
    double K[K_LEN], P[P_LEN];
    double iq[NCH], q[NCH], lo[NCH], hi[NCH];
    Py_buffer out[O_LEN];
    int have_out;
    /* the current job */
    const int64_t *acts;
    const uint8_t *active;
    /* threads */
    int nthreads, started;
    long owner_pid; /* the process whose threads these are (a forked child has none) */
    Worker *workers;
    pthread_mutex_t mu;
    pthread_cond_t cv;
    long gen;
    int stop;
    atomic_int pending;
    int running;       /* a job started by step_start and not yet finished */
    Py_buffer job_acts, job_mask;
    int job_have_mask;
    /* resets in C (Batch.set_reset): the env's constants, and the slots the job resets */
    double R[R_LEN], L[L_LEN];
    int reset_ready;
    const uint8_t *resets;
    Py_buffer job_reset;
    int job_have_reset;
    uint8_t *scratch; /* vstep's active mask */
    /* the last info spec (name, mask name, output index) parsed by collect_alloc, kept */
    PyObject *spec, *spec_name[O_LEN], *spec_mname[O_LEN];
    int spec_idx[O_LEN], spec_n;
};

static int reset_slot(BatchObject *b, Py_ssize_t i);
static void free_cworld(Slot *s);

/* ---------------------------------------------------------------- the cell set of MKV-v1 */
static inline uint64_t cell_hash(uint64_t k)
{
    k ^= k >> 33;
    k *= 0xff51afd7ed558ccdULL;
    k ^= k >> 33;
    return k;
}

/* 1 if the cell was new (and is now in), 0 if seen, -1 on error. */
static int cell_add(Slot *s, double cx, double cy)
{
    if (!(fabs(cx) < 2147483647.0 && fabs(cy) < 2147483647.0))
        return -1;
    uint64_t key = ((uint64_t)(uint32_t)(int32_t)cx << 32) | (uint64_t)(uint32_t)(int32_t)cy;
    key += 1; /* 0 marks an empty bucket; (uint64)-1 + 1 wraps to 0 only for (-1, -1) */
    if (key == 0)
        key = 0x8000000000000000ULL; /* unused by in-range cells (cx = INT32_MIN) */
    if ((s->ncells + 1) * 2 > s->cap) {
        int64_t cap = s->cap ? s->cap * 2 : 256;
        uint64_t *t = calloc((size_t)cap, sizeof(uint64_t));
        if (t == NULL)
            return -1;
        for (int64_t i = 0; i < s->cap; i++) {
            uint64_t k = s->cells[i];
            if (k) {
                uint64_t h = cell_hash(k) & (uint64_t)(cap - 1);
                while (t[h])
                    h = (h + 1) & (uint64_t)(cap - 1);
                t[h] = k;
            }
        }
        free(s->cells);
        s->cells = t;
        s->cap = cap;
    }
    uint64_t h = cell_hash(key) & (uint64_t)(s->cap - 1);
    while (s->cells[h]) {
        if (s->cells[h] == key)
            return 0;
        h = (h + 1) & (uint64_t)(s->cap - 1);
    }
    s->cells[h] = key;
    s->ncells += 1;
    return 1;
}

static void cells_clear(Slot *s)
{
    if (s->cells)
        memset(s->cells, 0, (size_t)s->cap * sizeof(uint64_t));
    s->ncells = 0;
}

/* ---------------------------------------------------------------- one robot, one period */
#define OUT(b, k, T) ((T *)(b)->out[k].buf)

static inline int is_clear(const Slot *s, double x, double y, double radius)
{
    cpPQInfo info;
    cpVect p = {x, y};
    cpFilter f = {1, 0xffffffffu, 0xffffffffu}; /* mkv_env.robot.ROBOT_FILTER */
    return cp_pq(s->space, p, radius, f, &info) == NULL;
}

/* World.floor_friction_scale: the friction multiplier of the first patch (x0, y0, x1, y1, scale)
 * under the drive wheel, xd ahead of the centre along the heading; 1 on bare floor. */
static double floor_scale(double xd, void *body, const double *patches, Py_ssize_t n)
{
    cpVect pos = cp_get_p(body);
    double th = cp_get_a(body);
    double x = pos.x + xd * cos(th), y = pos.y + xd * sin(th);
    for (Py_ssize_t k = 0; k < n; k++) {
        const double *pt = patches + 5 * k;
        if (pt[0] <= x && x <= pt[2] && pt[1] <= y && y <= pt[3])
            return pt[4];
    }
    return 1.0;
}

/* SensorSuite.draw_block in C: the next block of noise rows, bias + std * standard normal, drawn
 * row by row, channel by channel from the slot's bit generator (numpy fills its (rows, channels)
 * array in that order), as two roundings like numpy's ``block *= std; block += bias``. */
static void refill_noise(Slot *s)
{
#ifdef MKV_NPYRANDOM
    bitgen_t *g = s->gen;
    for (int r = 0; r < NOISE_ROWS; r++)
        for (int c = 0; c < NCH; c++) {
            double z = random_standard_normal(g);
            double t = z * s->nstd[c];
            s->noise[NCH * r + c] = t + s->nbias[c];
        }
    s->row = 0;
#else
    (void)s;
#endif
}

/* 1 when the slot has used its noise block and cannot draw the next itself (Python must). */
static inline int needs_noise(const Slot *s)
{
    return s->row >= NOISE_ROWS && s->gen == NULL;
}

/* SensorSuite.read on slot i's current state: the observation into row i of the obs buffer.
 * Returns 0 or an error code. */
static int read_sensors(BatchObject *b, Py_ssize_t i)
{
    Slot *s = &b->slots[i];
    if (s->row >= NOISE_ROWS) /* (only reached with a bit generator bound: see needs_noise) */
        refill_noise(s);
    const double *P = b->P;
    double *v = s->v;
    const int64_t *c = s->contacts;
    double tick = P[P_TICK];
    double dt_ = floor(v[S_DRIVE_ANGLE] / tick), rt_ = floor(v[S_ROLLER_ANGLE] / tick);
    double d0 = v[V_TICK_D], r0 = v[V_TICK_R];
    v[V_TICK_D] = dt_;
    v[V_TICK_R] = rt_;
    double i_d = v[S_I_DRIVE], i_s = v[S_I_STEER];
    const double *nz = s->noise + NCH * s->row;
    s->row += 1;
    double angle = cp_get_a(s->body);
    double truth[NCH];
    truth[0] = (dt_ - d0) + nz[0];
    truth[1] = (rt_ - r0) + nz[1];
    truth[2] = v[S_DELTA] + nz[2];
    truth[3] = py_mod(angle + nz[3] + M_PI, 2.0 * M_PI) - M_PI;
    truth[4] = (double)(c[2] > 0) + nz[4];
    truth[5] = (double)(c[3] > 0) + nz[5];
    truth[6] = (double)(c[4] > 0) + nz[6];
    truth[7] = i_d + nz[7];
    truth[8] = i_s + nz[8];
    truth[9] = P[P_BATT_V] - P[P_BATT_R] * (fabs(i_d) + fabs(i_s)) + nz[9];
    float *obs = OUT(b, O_OBS, float) + NCH * i;
    for (int k = 0; k < NCH; k++) {
        double y = truth[k] * b->iq[k];
        if (!isfinite(y))
            return s->err = ERR_NONFINITE;
        double r = rint(y);
        if (r == 0.0)
            r = 0.0;
        double val = r * b->q[k];
        double m = (b->lo[k] > val) ? b->lo[k] : val;
        obs[k] = (float)((b->hi[k] < m) ? b->hi[k] : m);
    }
    return 0;
}

/* Returns the slot's error code (0 = fine). Results go to the output buffers at row i. */
static int step_slot(BatchObject *b, Py_ssize_t i, long drive, long steer)
{
    Slot *s = &b->slots[i];
    const double *P = b->P;
    double *v = s->v;
    if (s->body == NULL)
        return s->err = ERR_UNBOUND;
    /* World.step: the floor under the drive wheel, looked up once per period */
    if (s->npatch)
        v[V_MU] = floor_scale(b->K[K_XD], s->body, s->patches, s->npatch);
    advance_one(b->K, s->body, s->space, drive, steer, P[P_DT], (long)P[P_SUBSTEPS], v[V_MU], v,
                1);

    /* SensorSuite.read */
    const int64_t *c = s->contacts;
    if (read_sensors(b, i))
        return s->err;
    double angle = cp_get_a(s->body);

    /* MKVEnv._pose + MotionTracker.update */
    cpVect pos = cp_get_p(s->body);
    double x = pos.x, y = pos.y, heading = remainder(angle, 2.0 * M_PI);
    double dx = x - v[V_X], dy = y - v[V_Y];
    double step = py_hypot(dx, dy);
    double mid = v[V_HEAD] + 0.5 * remainder(heading - v[V_HEAD], 2.0 * M_PI);
    double progress = dx * cos(mid) + dy * sin(mid);
    v[V_X] = x;
    v[V_Y] = y;
    v[V_HEAD] = heading;
    v[V_DIST] += step;
    v[V_LAST] = step;
    int stuck = drive != 0 && step < P[P_STUCK_SPEED] * P[P_PERIOD];
    v[V_STUCK_RUN] = stuck ? v[V_STUCK_RUN] + 1.0 : 0.0;
    double events = (double)c[0];
    int collision = events > v[V_EVENTS];
    if (collision)
        v[V_COLLS] += 1.0;
    v[V_EVENTS] = events;
    v[V_FWD] = progress > 1e-3 ? v[V_FWD] + progress : 0.0;
    int escaped = 0;
    if (v[V_IN_JAM] != 0.0) {
        if (!stuck && v[V_FWD] >= P[P_ESC_FWD] &&
            py_hypot(x - v[V_JAM_X], y - v[V_JAM_Y]) >= P[P_ESC_DIST] &&
            is_clear(s, x, y, P[P_FREE_CLEAR])) {
            v[V_IN_JAM] = 0.0;
            v[V_ESCAPES] += 1.0;
            escaped = 1;
        }
    } else if (v[V_STUCK_RUN] >= P[P_JAM_STEPS]) {
        v[V_IN_JAM] = 1.0;
        v[V_JAMS] += 1.0;
        v[V_JAM_X] = x;
        v[V_JAM_Y] = y;
    }

    /* the env class's _reward and _terminated */
    double reward;
    int terminated = 0;
    int kind = (int)P[P_KIND];
    if (kind == KIND_WANDER || kind == KIND_JAM) {
        reward = P[P_PROGRESS] * progress - P[P_STUCK_PEN] * (double)stuck -
                 P[P_COLL_PEN] * (double)collision;
        if (kind == KIND_JAM) {
            reward = reward + P[P_ESC_REWARD] * (double)escaped;
            terminated = escaped;
        }
    } else if (kind == KIND_WANDER_V1) {
        double new_cell = 0.0;
        if (progress > 0) {
            int r = cell_add(s, floor(x / P[P_CELL]), floor(y / P[P_CELL]));
            if (r < 0)
                return s->err = ERR_CELL;
            new_cell = (double)r;
        }
        int still = v[V_LAST] < P[P_STUCK_SPEED] * P[P_PERIOD];
        reward = P[P_COVERAGE] * new_cell - P[P_STILL_PEN] * (double)still -
                 P[P_STUCK_PEN] * (double)stuck - P[P_JAM_PEN] * v[V_IN_JAM] -
                 P[P_COLL_PEN] * (double)collision;
    } else {
        double d = py_hypot(v[V_X] - v[V_JAM_X], v[V_Y] - v[V_JAM_Y]);
        double q = d / P[P_ESC_DIST];
        double phi = (1.0 < q) ? 1.0 : q;
        double shaped = P[P_SHAPING] * (phi - v[V_PHI]);
        v[V_PHI] = phi;
        reward = P[P_ESC_REWARD] * (double)escaped - P[P_TIME_PEN] -
                 P[P_STUCK_PEN] * (double)stuck - P[P_COLL_PEN] * (double)collision + shaped;
        terminated = escaped;
    }

    OUT(b, O_REW, double)[i] = reward;
    OUT(b, O_TERM, uint8_t)[i] = (uint8_t)terminated;
    OUT(b, O_STUCK, uint8_t)[i] = (uint8_t)stuck;
    OUT(b, O_BUMPED, uint8_t)[i] = (uint8_t)(c[2] > 0 || c[3] > 0 || c[4] > 0);
    OUT(b, O_COLL, uint8_t)[i] = (uint8_t)collision;
    OUT(b, O_DIST, double)[i] = v[V_DIST];
    OUT(b, O_JAMS, int64_t)[i] = (int64_t)v[V_JAMS];
    OUT(b, O_ESC, int64_t)[i] = (int64_t)v[V_ESCAPES];
    OUT(b, O_COLLS, int64_t)[i] = (int64_t)v[V_COLLS];
    OUT(b, O_IN_JAM, uint8_t)[i] = (uint8_t)(v[V_IN_JAM] != 0.0);
    double *pose = OUT(b, O_POSE, double) + 3 * i;
    pose[0] = x;
    pose[1] = y;
    pose[2] = heading;
    OUT(b, O_CELLS, int64_t)[i] = s->ncells;
    OUT(b, O_ESCAPED, uint8_t)[i] = (uint8_t)(v[V_ESCAPES] > 0.0);
    return 0;
}

/* The current job's robots, claimed one by one by the threads. Each thread has a home group, a
 * fixed contiguous share of the robots, so each robot's memory (its Chipmunk space, shapes,
 * contact buffers) mostly stays in one core's caches (threads taking robots in turn measured
 * only 1.24x on two cores, contiguous shares more; see benchmarks/env_speed.py); a thread
 * that has finished its group takes the unclaimed robots of the others (the calling thread is
 * late when it resets the envs that ended while the workers step). Which thread steps a robot
 * never changes its result: each is claimed exactly once (an atomic counter per group). */
static inline void step_robot(BatchObject *b, Py_ssize_t i)
{
    const int64_t *a = b->acts;
    if (b->resets != NULL && b->resets[i]) {
        reset_slot(b, i);
        return;
    }
    if (b->active != NULL && !b->active[i])
        return;
    /* [drive, steer] in {0,1,2}: motor commands a0 - 1 and 1 - a1 (steer 0 = left = +1) */
    step_slot(b, i, (long)(a[2 * i] - 1), (long)(1 - a[2 * i + 1]));
}

static void run_group(BatchObject *b, int g)
{
    int T = b->nthreads;
    if (T <= 1 || b->workers == NULL) {
        for (Py_ssize_t i = 0; i < b->n; i++)
            step_robot(b, i);
        return;
    }
    for (int k = 0; k < T; k++) {
        int h = (g + k) % T;
        Py_ssize_t hi = b->n * (h + 1) / T;
        atomic_long *next = &b->workers[h].next;
        for (;;) {
            Py_ssize_t i = (Py_ssize_t)atomic_fetch_add_explicit(next, 1, memory_order_relaxed);
            if (i >= hi)
                break;
            step_robot(b, i);
        }
    }
}

/* One turn of a wait loop: the first turns spin on the CPU's pause instruction (a few
 * microseconds: back-to-back steps resume at once), later ones yield the core. */
static inline void wait_a_little(int spin)
{
    if (spin < 256) {
#if defined(__x86_64__) || defined(__i386__)
        __builtin_ia32_pause();
#elif defined(__aarch64__)
        __asm__ __volatile__("yield");
#endif
    } else {
        sched_yield();
    }
}

static void *worker_main(void *arg)
{
    Worker *w = arg;
    BatchObject *b = w->b;
    long seen = 0;
    for (;;) {
        /* spin a little (back-to-back steps), then sleep on the condition variable */
        long gen = 0;
        for (int spin = 0; spin < 20000; spin++) {
            gen = __atomic_load_n(&b->gen, __ATOMIC_ACQUIRE);
            if (gen != seen || __atomic_load_n(&b->stop, __ATOMIC_ACQUIRE))
                break;
            wait_a_little(spin);
        }
        pthread_mutex_lock(&b->mu);
        while (b->gen == seen && !b->stop)
            pthread_cond_wait(&b->cv, &b->mu);
        gen = b->gen;
        int stop = b->stop;
        pthread_mutex_unlock(&b->mu);
        if (stop)
            return NULL;
        seen = gen;
        run_group(b, w->group);
        atomic_fetch_sub_explicit(&b->pending, 1, memory_order_acq_rel);
    }
}

static int start_workers(BatchObject *b)
{
    if (b->started && b->owner_pid != (long)getpid()) {
        /* a fork: this process has none of the parent's threads; start its own */
        free(b->workers);
        b->workers = NULL;
        pthread_mutex_init(&b->mu, NULL);
        pthread_cond_init(&b->cv, NULL);
        b->started = 0;
        b->gen = 0;
        b->stop = 0;
    }
    if (b->nthreads <= 1 || b->started)
        return 0;
    b->owner_pid = (long)getpid();
    b->workers = aligned_alloc(64, (size_t)b->nthreads * sizeof(Worker)); /* cursor per line */
    if (b->workers != NULL)
        memset(b->workers, 0, (size_t)b->nthreads * sizeof(Worker));
    if (b->workers == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    for (int g = 1; g < b->nthreads; g++) {
        b->workers[g].b = b;
        b->workers[g].group = g;
        if (pthread_create(&b->workers[g].th, NULL, worker_main, &b->workers[g]) != 0) {
            b->nthreads = g; /* the ones started keep working; the rest run on fewer threads */
            break;
        }
    }
    b->started = 1;
    return 0;
}

/* Hand the current job to the worker threads (they start at once). */
static void launch_job(BatchObject *b)
{
    if (b->nthreads <= 1)
        return;
    for (int g = 0; g < b->nthreads; g++) /* every group's robots unclaimed again */
        atomic_store_explicit(&b->workers[g].next, (long)(b->n * g / b->nthreads),
                              memory_order_relaxed);
    atomic_store(&b->pending, b->nthreads - 1);
    pthread_mutex_lock(&b->mu);
    __atomic_add_fetch(&b->gen, 1, __ATOMIC_RELEASE);
    pthread_cond_broadcast(&b->cv);
    pthread_mutex_unlock(&b->mu);
}

/* The calling thread joins the job, then waits for the workers (GIL released by the caller). */
static void finish_job(BatchObject *b)
{
    run_group(b, 0);
    if (b->nthreads > 1)
        for (int spin = 0; atomic_load_explicit(&b->pending, memory_order_acquire) > 0; spin++)
            wait_a_little(spin);
}

static void release_job(BatchObject *b);

/* ---------------------------------------------------------------- the Python type */
static PyObject *raise_slot_error(Slot *s, Py_ssize_t i)
{
    switch (s->err) {
    case ERR_NONFINITE:
        PyErr_SetString(PyExc_ValueError, "cannot quantize a non-finite sensor value");
        break;
    case ERR_CELL:
        PyErr_Format(PyExc_ValueError, "robot %zd left the arena (coverage cell out of range)", i);
        break;
    case ERR_UNBOUND:
        PyErr_Format(PyExc_RuntimeError, "step kernel slot %zd has no world: call reset()", i);
        break;
    case ERR_NOPOSE:
        PyErr_SetString(PyExc_RuntimeError, "could not find a free start pose; reduce n_clutter");
        break;
    default:
        PyErr_NoMemory();
    }
    s->err = 0;
    return NULL;
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

static void batch_dealloc(BatchObject *b)
{
    /* a forked copy: none of the parent's threads are here to stop or to wait for, and its
       mutex and condition variable still count the parent's waiters (destroying them would
       wait for those forever): leave them, the memory goes with the object */
    int forked = b->started && b->owner_pid != (long)getpid();
    if (forked) {
        b->started = 0;
        b->running = 0;
    }
    if (b->running) { /* a started step: let it end before the memory goes */
        finish_job(b);
        release_job(b);
        b->running = 0;
    }
    if (b->started && b->workers) {
        pthread_mutex_lock(&b->mu);
        b->stop = 1;
        pthread_cond_broadcast(&b->cv);
        pthread_mutex_unlock(&b->mu);
        for (int g = 1; g < b->nthreads; g++)
            pthread_join(b->workers[g].th, NULL);
    }
    free(b->workers);
    free(b->scratch);
    Py_XDECREF(b->spec);
    if (!forked) {
        pthread_mutex_destroy(&b->mu);
        pthread_cond_destroy(&b->cv);
    }
    if (b->have_out)
        for (int k = 0; k < O_LEN; k++)
            PyBuffer_Release(&b->out[k]);
    if (b->slots) {
        for (Py_ssize_t i = 0; i < b->n; i++) {
            free_cworld(&b->slots[i]);
            free(b->slots[i].lay);
            free(b->slots[i].sshapes);
            Py_XDECREF(b->slots[i].retired);
            free(b->slots[i].patches);
            free(b->slots[i].cells);
            Py_XDECREF(b->slots[i].keep);
            Py_XDECREF(b->slots[i].gen_keep);
        }
        PyMem_Free(b->slots);
    }
    Py_TYPE(b)->tp_free((PyObject *)b);
}

/* Batch(n, K, params, sensor(4 x 10: inv_q, q, low, high), num_threads) */
static PyObject *batch_new(PyTypeObject *type, PyObject *args, PyObject *kw)
{
    Py_ssize_t n;
    int nthreads;
    PyObject *K, *P, *S;
    if (!PyArg_ParseTuple(args, "nOOOi", &n, &K, &P, &S, &nthreads))
        return NULL;
    if (n < 1 || nthreads < 1) {
        PyErr_SetString(PyExc_ValueError, "Batch needs n >= 1 and num_threads >= 1");
        return NULL;
    }
    if (check_bound() < 0 || cp_pq == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "mkv_env._fastsim: bind() has not been called");
        return NULL;
    }
    BatchObject *b = (BatchObject *)type->tp_alloc(type, 0);
    if (b == NULL)
        return NULL;
    pthread_mutex_init(&b->mu, NULL);
    pthread_cond_init(&b->cv, NULL);
    b->n = n;
    b->nthreads = nthreads > n ? (int)n : nthreads;
    b->slots = PyMem_Calloc((size_t)n, sizeof(Slot));
    if (b->slots == NULL) {
        Py_DECREF(b);
        return PyErr_NoMemory();
    }
    double sens[4 * NCH];
    if (get_doubles(K, b->K, K_LEN, "K") < 0 || get_doubles(P, b->P, P_LEN, "params") < 0 ||
        get_doubles(S, sens, 4 * NCH, "sensor constants") < 0) {
        Py_DECREF(b);
        return NULL;
    }
    memcpy(b->iq, sens, sizeof b->iq);
    memcpy(b->q, sens + NCH, sizeof b->q);
    memcpy(b->lo, sens + 2 * NCH, sizeof b->lo);
    memcpy(b->hi, sens + 3 * NCH, sizeof b->hi);
    for (Py_ssize_t i = 0; i < n; i++)
        b->slots[i].row = NOISE_ROWS;
    return (PyObject *)b;
}

static Slot *get_slot(BatchObject *b, PyObject *idx, Py_ssize_t *out)
{
    Py_ssize_t i = PyLong_AsSsize_t(idx);
    if (i == -1 && PyErr_Occurred())
        return NULL;
    if (i < 0 || i >= b->n) {
        PyErr_Format(PyExc_IndexError, "slot %zd out of range", i);
        return NULL;
    }
    if (out)
        *out = i;
    return &b->slots[i];
}

/* outputs(obs, rew, term, stuck, bumped, collision, distance, jams, escapes, collisions, in_jam,
 *         pose, cells, escaped): C-contiguous numpy arrays with n rows, written by every step. */
static PyObject *batch_outputs(BatchObject *b, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer tmp[O_LEN];
    if (nargs != O_LEN) {
        PyErr_Format(PyExc_TypeError, "outputs() takes %d arrays", O_LEN);
        return NULL;
    }
    int k;
    for (k = 0; k < O_LEN; k++) {
        if (PyObject_GetBuffer(args[k], &tmp[k],
                               PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE) < 0)
            goto fail;
        Py_ssize_t item = O_FMT[k] == 'f' ? 4 : O_FMT[k] == '?' ? 1 : 8;
        const char *fm = tmp[k].format;
        int fmt_ok = fm != NULL && fm[0] != 0 && fm[1] == 0 &&
                     (fm[0] == O_FMT[k] || (O_FMT[k] == 'q' && fm[0] == 'l'));
        if (!fmt_ok ||
            tmp[k].itemsize != item || tmp[k].len != b->n * O_WIDTH[k] * item) {
            PyErr_Format(PyExc_ValueError, "output %d must be %zd x %d of format '%c'", k, b->n,
                         O_WIDTH[k], O_FMT[k]);
            k++;
            goto fail;
        }
    }
    if (b->have_out)
        for (int j = 0; j < O_LEN; j++)
            PyBuffer_Release(&b->out[j]);
    memcpy(b->out, tmp, sizeof tmp);
    b->have_out = 1;
    Py_RETURN_NONE;
fail:
    for (int j = 0; j < k; j++)
        PyBuffer_Release(&tmp[j]);
    return NULL;
}

/* bind(i, body_ptr, space_ptr, counts_array, patches(list of 5-tuples)) */
static PyObject *batch_bind(BatchObject *b, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 5) {
        PyErr_SetString(PyExc_TypeError, "bind() takes 5 arguments");
        return NULL;
    }
    Slot *s = get_slot(b, args[0], NULL);
    if (s == NULL)
        return NULL;
    void *body = PyLong_AsVoidPtr(args[1]), *space = PyLong_AsVoidPtr(args[2]);
    if (PyErr_Occurred())
        return NULL;
    Py_buffer cv;
    if (PyObject_GetBuffer(args[3], &cv, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE) < 0)
        return NULL;
    int ok = cv.itemsize == 8 && cv.len == 40 && cv.format &&
             (strcmp(cv.format, "q") == 0 || strcmp(cv.format, "l") == 0);
    int64_t *counts = cv.buf;
    PyBuffer_Release(&cv); /* the array is kept alive (s->keep) and never resized */
    if (!ok || body == NULL || space == NULL) {
        PyErr_SetString(PyExc_ValueError, "bind: bad body, space or counts (int64 x 5)");
        return NULL;
    }
    PyObject *fast = PySequence_Fast(args[4], "patches must be a sequence");
    if (fast == NULL)
        return NULL;
    Py_ssize_t np_ = PySequence_Fast_GET_SIZE(fast);
    double *pt = np_ ? malloc((size_t)np_ * 5 * sizeof(double)) : NULL;
    if (np_ && pt == NULL) {
        Py_DECREF(fast);
        return PyErr_NoMemory();
    }
    for (Py_ssize_t k = 0; k < np_; k++) {
        PyObject *row = PySequence_Fast(PySequence_Fast_GET_ITEM(fast, k), "patch");
        if (row == NULL || PySequence_Fast_GET_SIZE(row) != 5) {
            Py_XDECREF(row);
            free(pt);
            Py_DECREF(fast);
            if (!PyErr_Occurred())
                PyErr_SetString(PyExc_ValueError, "a patch is (x0, y0, x1, y1, scale)");
            return NULL;
        }
        for (int j = 0; j < 5; j++)
            pt[5 * k + j] = PyFloat_AsDouble(PySequence_Fast_GET_ITEM(row, j));
        Py_DECREF(row);
    }
    Py_DECREF(fast);
    if (PyErr_Occurred()) {
        free(pt);
        return NULL;
    }
    /* (while a job runs, only slots it neither steps nor resets are bound: step_start) */
    free_cworld(s); /* a world the kernel built and Python never adopted */
    free(s->patches);
    s->patches = pt;
    s->npatch = np_;
    s->body = body;
    s->space = space;
    s->contacts = counts;
    Py_INCREF(args[3]);
    Py_XSETREF(s->keep, args[3]);
    Py_RETURN_NONE;
}

/* load(i, values(V_LEN float64), row, cells(list of (cx, cy))): a slot's state */
static PyObject *batch_load(BatchObject *b, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "load() takes 4 arguments");
        return NULL;
    }
    Slot *s = get_slot(b, args[0], NULL);
    if (s == NULL)
        return NULL;
    double v[V_LEN];
    if (get_doubles(args[1], v, V_LEN, "state") < 0)
        return NULL;
    long row = PyLong_AsLong(args[2]);
    if (row == -1 && PyErr_Occurred())
        return NULL;
    if (row < 0 || row > NOISE_ROWS) {
        PyErr_SetString(PyExc_ValueError, "noise row out of range");
        return NULL;
    }
    PyObject *fast = PySequence_Fast(args[3], "cells must be a sequence");
    if (fast == NULL)
        return NULL;
    cells_clear(s);
    for (Py_ssize_t k = 0; k < PySequence_Fast_GET_SIZE(fast); k++) {
        double cx, cy;
        if (!PyArg_ParseTuple(PySequence_Fast_GET_ITEM(fast, k), "dd", &cx, &cy) ||
            cell_add(s, cx, cy) < 0) {
            Py_DECREF(fast);
            if (!PyErr_Occurred())
                PyErr_SetString(PyExc_ValueError, "bad coverage cell");
            return NULL;
        }
    }
    Py_DECREF(fast);
    memcpy(s->v, v, sizeof v);
    s->row = row;
    s->err = 0;
    Py_RETURN_NONE;
}

/* set_params(params): new parameter values (the env's reward weights and thresholds). */
static PyObject *batch_set_params(BatchObject *b, PyObject *P)
{
    if (b->running) {
        PyErr_SetString(PyExc_RuntimeError, "step kernel: a step is running");
        return NULL;
    }
    if (get_doubles(P, b->P, P_LEN, "params") < 0)
        return NULL;
    Py_RETURN_NONE;
}

/* set_noise(i, block (256 x 10 float64)): a new block of noise rows, read from row 0 */
static PyObject *batch_set_noise(BatchObject *b, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "set_noise() takes 2 arguments");
        return NULL;
    }
    Slot *s = get_slot(b, args[0], NULL);
    if (s == NULL || get_doubles(args[1], s->noise, NOISE_ROWS * NCH, "noise block") < 0)
        return NULL;
    s->row = 0;
    Py_RETURN_NONE;
}

#ifdef MKV_NPYRANDOM
/* The bitgen_t of a numpy BitGenerator (through its ``capsule``), or NULL with an error set. */
static bitgen_t *bitgen_of(PyObject *bit_generator)
{
    PyObject *cap = PyObject_GetAttrString(bit_generator, "capsule");
    if (cap == NULL)
        return NULL;
    bitgen_t *g = PyCapsule_GetPointer(cap, "BitGenerator");
    Py_DECREF(cap);
    return g;
}
#endif

/* set_noise_source(i, bit_generator or None, std (10 float64), bias (10 float64)) -> bool: slot i
 * draws its own noise blocks from this numpy BitGenerator (the episode's SensorSuite._rng's)
 * from now on; True when bound. False (Python draws, through set_noise) when the extension was
 * built without numpy's random library, for None, and for a generator another slot of the batch
 * draws from too (both then draw through Python, in slot order, as the reference does). */
static PyObject *batch_set_noise_source(BatchObject *b, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "set_noise_source() takes 4 arguments");
        return NULL;
    }
    Py_ssize_t i;
    Slot *s = get_slot(b, args[0], &i);
    if (s == NULL)
        return NULL;
    double std[NCH], bias[NCH];
    if (get_doubles(args[2], std, NCH, "noise std") < 0 ||
        get_doubles(args[3], bias, NCH, "noise bias") < 0)
        return NULL;
    s->gen = NULL;
    Py_CLEAR(s->gen_keep);
#ifdef MKV_NPYRANDOM
    if (args[1] == Py_None)
        Py_RETURN_FALSE;
    void *g = bitgen_of(args[1]);
    if (g == NULL)
        return NULL;
    int shared = 0;
    for (Py_ssize_t j = 0; j < b->n; j++)
        if (j != i && b->slots[j].gen == g) {
            if (b->running) {
                PyErr_SetString(PyExc_RuntimeError, "step kernel: a step is running");
                return NULL;
            }
            b->slots[j].gen = NULL;
            Py_CLEAR(b->slots[j].gen_keep);
            shared = 1;
        }
    if (shared)
        Py_RETURN_FALSE;
    memcpy(s->nstd, std, sizeof std);
    memcpy(s->nbias, bias, sizeof bias);
    Py_INCREF(args[1]);
    s->gen_keep = args[1];
    s->gen = g;
    Py_RETURN_TRUE;
#else
    Py_RETURN_FALSE;
#endif
}

/* normals(bit_generator, k) -> list of k floats from numpy's random_standard_normal in C (the
 * import-time check that the linked library draws what Generator.standard_normal draws), or
 * None when built without it. */
static PyObject *fs_normals(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "normals() takes 2 arguments");
        return NULL;
    }
#ifdef MKV_NPYRANDOM
    Py_ssize_t k = PyLong_AsSsize_t(args[1]);
    if (k == -1 && PyErr_Occurred())
        return NULL;
    bitgen_t *g = bitgen_of(args[0]);
    if (g == NULL)
        return NULL;
    PyObject *out = PyList_New(k > 0 ? k : 0);
    if (out == NULL)
        return NULL;
    for (Py_ssize_t m = 0; m < k; m++) {
        PyObject *f = PyFloat_FromDouble(random_standard_normal(g));
        if (f == NULL) {
            Py_DECREF(out);
            return NULL;
        }
        PyList_SET_ITEM(out, m, f);
    }
    return out;
#else
    Py_RETURN_NONE;
#endif
}

/* state(i) -> (values tuple, row, noise bytes, cells list) */
static PyObject *batch_state(BatchObject *b, PyObject *idx)
{
    Slot *s = get_slot(b, idx, NULL);
    if (s == NULL)
        return NULL;
    PyObject *vals = PyTuple_New(V_LEN);
    PyObject *cells = PyList_New(0);
    if (vals == NULL || cells == NULL)
        goto fail;
    for (int k = 0; k < V_LEN; k++)
        PyTuple_SET_ITEM(vals, k, PyFloat_FromDouble(s->v[k]));
    for (int64_t k = 0; k < s->cap; k++) {
        uint64_t key = s->cells[k];
        if (!key)
            continue;
        if (key == 0x8000000000000000ULL)
            key = 0;
        key -= 1;
        PyObject *t = Py_BuildValue("(ll)", (long)(int32_t)(uint32_t)(key >> 32),
                                    (long)(int32_t)(uint32_t)(key & 0xffffffffu));
        if (t == NULL || PyList_Append(cells, t) < 0) {
            Py_XDECREF(t);
            goto fail;
        }
        Py_DECREF(t);
    }
    PyObject *noise = PyBytes_FromStringAndSize((const char *)s->noise, sizeof s->noise);
    if (noise == NULL)
        goto fail;
    return Py_BuildValue("(NlNN)", vals, s->row, noise, cells);
fail:
    Py_XDECREF(vals);
    Py_XDECREF(cells);
    return NULL;
}

/* step1(i, drive, steer) -> info tuple, or None when the slot needs a new noise block first.
 * drive/steer are motor commands (-1/0/+1). The observation goes to row i of the obs buffer.
 * Tuple: (reward, terminated, stuck, bumped, collision, distance_m, jams, escapes, collisions,
 *         in_jam, x, y, heading, cells_visited, escaped) */
static PyObject *batch_step1(BatchObject *b, PyObject *const *args, Py_ssize_t nargs)
{
    Py_ssize_t i;
    if (nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "step1() takes 3 arguments");
        return NULL;
    }
    Slot *s = get_slot(b, args[0], &i);
    if (s == NULL)
        return NULL;
    long drive = PyLong_AsLong(args[1]), steer = PyLong_AsLong(args[2]);
    if (PyErr_Occurred())
        return NULL;
    if (!b->have_out) {
        PyErr_SetString(PyExc_RuntimeError, "step kernel: outputs() not set");
        return NULL;
    }
    if (needs_noise(s))
        Py_RETURN_NONE;
    if (step_slot(b, i, drive, steer))
        return raise_slot_error(s, i);
    double *pose = OUT(b, O_POSE, double) + 3 * i;
    return Py_BuildValue(
        "(dOOOOdLLLOdddLO)", OUT(b, O_REW, double)[i],
        OUT(b, O_TERM, uint8_t)[i] ? Py_True : Py_False,
        OUT(b, O_STUCK, uint8_t)[i] ? Py_True : Py_False,
        OUT(b, O_BUMPED, uint8_t)[i] ? Py_True : Py_False,
        OUT(b, O_COLL, uint8_t)[i] ? Py_True : Py_False, OUT(b, O_DIST, double)[i],
        (long long)OUT(b, O_JAMS, int64_t)[i], (long long)OUT(b, O_ESC, int64_t)[i],
        (long long)OUT(b, O_COLLS, int64_t)[i], OUT(b, O_IN_JAM, uint8_t)[i] ? Py_True : Py_False,
        pose[0], pose[1], pose[2], (long long)OUT(b, O_CELLS, int64_t)[i],
        OUT(b, O_ESCAPED, uint8_t)[i] ? Py_True : Py_False);
}

/* read(i) -> True, or False when slot i needs a new noise block first: SensorSuite.read on the
 * slot's current state (a reset's first observation), into row i of the obs buffer. */
static PyObject *batch_read(BatchObject *b, PyObject *idx)
{
    Py_ssize_t i;
    Slot *s = get_slot(b, idx, &i);
    if (s == NULL)
        return NULL;
    if (!b->have_out || s->body == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "step kernel: outputs or world not set");
        return NULL;
    }
    if (needs_noise(s))
        Py_RETURN_FALSE;
    if (read_sensors(b, i))
        return raise_slot_error(s, i);
    Py_RETURN_TRUE;
}

/* Append i to the list *list (made when NULL). 0, or -1 with an error set. */
static int append_index(PyObject **list, Py_ssize_t i)
{
    if (*list == NULL && (*list = PyList_New(0)) == NULL)
        return -1;
    PyObject *k = PyLong_FromSsize_t(i);
    int rc = k == NULL ? -1 : PyList_Append(*list, k);
    Py_XDECREF(k);
    return rc;
}

/* Validate a job's buffers and find the active slots that need noise. Returns 0 with the job's
 * buffers held in b->job_* (and *need a new list, or NULL), or -1 with an error set. */
static int prepare_job(BatchObject *b, PyObject *acts, PyObject *mask, PyObject *resets,
                       PyObject **need)
{
    Py_buffer *av = &b->job_acts, *mv = &b->job_mask, *rv = &b->job_reset;
    *need = NULL;
    b->job_have_reset = 0;
    if (!b->have_out) {
        PyErr_SetString(PyExc_RuntimeError, "step kernel: outputs() not set");
        return -1;
    }
    if (b->running) {
        PyErr_SetString(PyExc_RuntimeError, "step kernel: a step is already running");
        return -1;
    }
    if (PyObject_GetBuffer(acts, av, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0)
        return -1;
    b->job_have_mask = 0;
    if (av->itemsize != 8 || av->len != b->n * 16 || av->format == NULL ||
        (strcmp(av->format, "q") != 0 && strcmp(av->format, "l") != 0)) {
        PyErr_Format(PyExc_ValueError, "actions must be int64 of shape (%zd, 2)", b->n);
        goto fail;
    }
    if (mask != Py_None) {
        if (PyObject_GetBuffer(mask, mv, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0)
            goto fail;
        b->job_have_mask = 1;
        if (mv->itemsize != 1 || mv->len != b->n || mv->format == NULL ||
            strcmp(mv->format, "?") != 0) {
            PyErr_Format(PyExc_ValueError, "active must be bool of shape (%zd,)", b->n);
            goto fail;
        }
    }
    if (resets != NULL && resets != Py_None) {
        if (PyObject_GetBuffer(resets, rv, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0)
            goto fail;
        b->job_have_reset = 1;
        if (rv->itemsize != 1 || rv->len != b->n || rv->format == NULL ||
            strcmp(rv->format, "?") != 0) {
            PyErr_Format(PyExc_ValueError, "resets must be bool of shape (%zd,)", b->n);
            goto fail;
        }
    }
    const int64_t *a = av->buf;
    const uint8_t *act = b->job_have_mask ? mv->buf : NULL;
    const uint8_t *rst = b->job_have_reset ? rv->buf : NULL;
    for (Py_ssize_t i = 0; rst && i < b->n; i++)
        if (rst[i] && (!b->reset_ready || b->slots[i].gen == NULL)) {
            PyErr_Format(PyExc_RuntimeError, "step kernel slot %zd cannot be reset in C "
                         "(no reset constants or no bit generator bound)", i);
            goto fail;
        }
    for (Py_ssize_t i = 0; i < 2 * b->n; i++)
        if (a[i] < 0 || a[i] > 2) {
            PyErr_Format(PyExc_ValueError, "action value %lld out of {0, 1, 2}", (long long)a[i]);
            goto fail;
        }
    for (Py_ssize_t i = 0; i < b->n; i++) {
        if ((act && !act[i]) || (rst && rst[i]))
            continue;
        if (b->slots[i].body == NULL) {
            PyErr_Format(PyExc_RuntimeError, "step kernel slot %zd has no world: call reset()", i);
            goto fail;
        }
        if (needs_noise(&b->slots[i]) && append_index(need, i) < 0)
            goto fail;
    }
    if (start_workers(b) < 0)
        goto fail;
    b->acts = a;
    b->active = act;
    b->resets = rst;
    return 0;
fail:
    Py_CLEAR(*need);
    PyBuffer_Release(av);
    if (b->job_have_mask)
        PyBuffer_Release(mv);
    if (b->job_have_reset)
        PyBuffer_Release(rv);
    b->job_have_mask = 0;
    b->job_have_reset = 0;
    return -1;
}

static void release_job(BatchObject *b)
{
    PyBuffer_Release(&b->job_acts);
    if (b->job_have_mask)
        PyBuffer_Release(&b->job_mask);
    if (b->job_have_reset)
        PyBuffer_Release(&b->job_reset);
    b->job_have_mask = 0;
    b->job_have_reset = 0;
    b->acts = NULL;
    b->active = NULL;
    b->resets = NULL;
}

/* After a job: errors, and reward 0 / not terminated for the inactive slots. */
static PyObject *conclude_job(BatchObject *b)
{
    const uint8_t *act = b->active;
    PyObject *result = Py_None;
    for (Py_ssize_t i = 0; i < b->n; i++) {
        if (b->slots[i].err) {
            if (result == Py_None)
                result = raise_slot_error(&b->slots[i], i);
            else
                b->slots[i].err = 0;
        }
        if (act && !act[i]) {
            OUT(b, O_REW, double)[i] = 0.0;
            OUT(b, O_TERM, uint8_t)[i] = 0;
        }
        Py_CLEAR(b->slots[i].retired);
    }
    release_job(b);
    Py_XINCREF(result);
    return result;
}

/* step(actions (n x 2 int64, values 0..2), active (n bool) or None) -> None, or the list of
 * active slots that need a new noise block first (nothing stepped then). Every active robot is
 * stepped with the GIL released, on num_threads threads. */
static PyObject *batch_step(BatchObject *b, PyObject *const *args, Py_ssize_t nargs)
{
    PyObject *need;
    if (nargs != 2 && nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "step() takes 2 or 3 arguments");
        return NULL;
    }
    if (prepare_job(b, args[0], args[1], nargs == 3 ? args[2] : NULL, &need) < 0)
        return NULL;
    if (need != NULL) {
        release_job(b);
        return need;
    }
    Py_BEGIN_ALLOW_THREADS
    launch_job(b);
    finish_job(b);
    Py_END_ALLOW_THREADS
    return conclude_job(b);
}

/* step_start(actions, active) -> None (the worker threads are stepping the active robots; call
 * step_finish() next, and touch no active slot in between), or the list of slots that need
 * noise first (nothing started). With one thread nothing runs until step_finish(). Inactive
 * slots may be reset (bind, load, set_noise, read) while the workers run. */
static PyObject *batch_step_start(BatchObject *b, PyObject *const *args, Py_ssize_t nargs)
{
    PyObject *need;
    if (nargs != 2 && nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "step_start() takes 2 or 3 arguments");
        return NULL;
    }
    if (prepare_job(b, args[0], args[1], nargs == 3 ? args[2] : NULL, &need) < 0)
        return NULL;
    if (need != NULL) {
        release_job(b);
        return need;
    }
    b->running = 1;
    launch_job(b);
    Py_RETURN_NONE;
}

/* step_finish() -> None: this thread joins the started step and waits for it to end. */
static PyObject *batch_step_finish(BatchObject *b, PyObject *unused)
{
    if (!b->running) {
        PyErr_SetString(PyExc_RuntimeError, "step kernel: step_finish() without step_start()");
        return NULL;
    }
    Py_BEGIN_ALLOW_THREADS
    finish_job(b);
    Py_END_ALLOW_THREADS
    b->running = 0;
    return conclude_job(b);
}

#ifdef MKV_NUMPY
/* A fresh numpy copy of output buffer k (shape (n,) or (n, width)). */
/* A fresh numpy array shaped like output buffer k ((n,) or (n, width)); filled later. */
static PyObject *out_new(BatchObject *b, int k)
{
    static const int types[256] = {['f'] = NPY_FLOAT32, ['d'] = NPY_FLOAT64, ['?'] = NPY_BOOL,
                                   ['q'] = NPY_INT64};
    npy_intp dims[2] = {b->n, O_WIDTH[k]};
    return PyArray_SimpleNew(O_WIDTH[k] > 1 ? 2 : 1, dims, types[(int)O_FMT[k]]);
}

/* collect(elapsed, max_steps, active, autoreset, spec, want_info) -> (obs, rewards, terminated,
 * truncated, cols, info or None): a vector env's per-step bookkeeping after step(), in one call
 * (MKVVectorEnv._step_kernel, the same operations as its Python fallback): fresh copies of this
 * step's outputs; elapsed (int64, n) += 1 for every stepped robot (active, bool n, or None for
 * all); truncated = elapsed >= max_steps (never when max_steps < 0) for stepped robots;
 * autoreset (bool n, or None) = terminated | truncated; cols = {name: copy of output index} for
 * each (name, mask_name, index) of spec; info = cols plus {mask_name: fresh all-True bool n}
 * when want_info (Gymnasium's vector info of robots that all report every key). */
/* A step's result arrays, made (collect_alloc, with the GIL) before they are filled from the
 * output buffers (collect_fill, which touches no Python object: vstep makes them while the worker
 * threads step). arr[k] is the array of output k, or NULL when the step does not return it. */
typedef struct {
    PyObject *arr[O_LEN], *trunc, *cols, *info;
} Collected;

static void collect_clear(Collected *c)
{
    for (int k = 0; k < O_LEN; k++)
        Py_CLEAR(c->arr[k]);
    Py_CLEAR(c->trunc);
    Py_CLEAR(c->cols);
    Py_CLEAR(c->info);
}

static int collect_alloc(BatchObject *b, PyObject *spec, int want, Collected *c)
{
    memset(c, 0, sizeof *c);
    npy_intp dim = b->n;
    if (!PyTuple_Check(spec)) {
        PyErr_SetString(PyExc_TypeError, "spec must be a tuple");
        return -1;
    }
    c->arr[O_OBS] = out_new(b, O_OBS);
    c->arr[O_REW] = out_new(b, O_REW);
    c->arr[O_TERM] = out_new(b, O_TERM);
    c->trunc = PyArray_SimpleNew(1, &dim, NPY_BOOL);
    c->cols = PyDict_New();
    c->info = want ? PyDict_New() : NULL;
    if (!c->arr[O_OBS] || !c->arr[O_REW] || !c->arr[O_TERM] || !c->trunc || !c->cols ||
        (want && !c->info))
        goto fail;
    if (spec != b->spec) { /* parse it once (a vector env passes the same tuple every step) */
        Py_ssize_t m = PyTuple_GET_SIZE(spec);
        if (m > O_LEN) {
            PyErr_SetString(PyExc_ValueError, "spec has too many columns");
            goto fail;
        }
        Py_CLEAR(b->spec);
        for (Py_ssize_t k = 0; k < m; k++) {
            PyObject *name, *mname;
            int idx;
            if (!PyArg_ParseTuple(PyTuple_GET_ITEM(spec, k), "UUi", &name, &mname, &idx))
                goto fail;
            if (idx < 0 || idx >= O_LEN) {
                PyErr_SetString(PyExc_ValueError, "output index out of range");
                goto fail;
            }
            b->spec_name[k] = name; /* borrowed: the tuple (kept in b->spec) holds them */
            b->spec_mname[k] = mname;
            b->spec_idx[k] = idx;
        }
        b->spec_n = (int)m;
        Py_INCREF(spec);
        b->spec = spec;
    }
    for (int k = 0; k < b->spec_n; k++) {
        PyObject *name = b->spec_name[k], *mname = b->spec_mname[k];
        int idx = b->spec_idx[k];
        if (c->arr[idx] == NULL && (c->arr[idx] = out_new(b, idx)) == NULL)
            goto fail;
        PyObject *col = c->arr[idx];
        if (PyDict_SetItem(c->cols, name, col) < 0 ||
            (want && PyDict_SetItem(c->info, name, col) < 0))
            goto fail;
        if (want) {
            PyObject *m = PyArray_SimpleNew(1, &dim, NPY_BOOL);
            if (m == NULL)
                goto fail;
            memset(PyArray_DATA((PyArrayObject *)m), 1, (size_t)b->n);
            int bad = PyDict_SetItem(c->info, mname, m) < 0;
            Py_DECREF(m);
            if (bad)
                goto fail;
        }
    }
    return 0;
fail:
    collect_clear(c);
    return -1;
}

/* Fill the arrays from the output buffers; el (int64 n) += 1 for the stepped slots (act, bool n,
 * or NULL for all), 0 for the slots reset (rst, or NULL); truncation; ar (or NULL) = the
 * autoreset flags (terminated | truncated). */
static void collect_fill(BatchObject *b, Collected *c, int64_t *el, long long max_steps,
                         const uint8_t *act, uint8_t *ar, const uint8_t *rst)
{
    for (int k = 0; k < O_LEN; k++)
        if (c->arr[k] != NULL)
            memcpy(PyArray_DATA((PyArrayObject *)c->arr[k]), b->out[k].buf,
                   (size_t)b->out[k].len);
    const uint8_t *te = PyArray_DATA((PyArrayObject *)c->arr[O_TERM]);
    uint8_t *tr = PyArray_DATA((PyArrayObject *)c->trunc);
    for (Py_ssize_t i = 0; i < b->n; i++) {
        int moved = act == NULL || act[i];
        el[i] += moved;
        if (rst != NULL && rst[i])
            el[i] = 0;
        tr[i] = (uint8_t)(moved && max_steps >= 0 && el[i] >= max_steps);
        if (ar != NULL)
            ar[i] = (uint8_t)(te[i] | tr[i]);
    }
}

/* (obs, rewards, terminated, truncated, cols, info or None); c is cleared. */
static PyObject *collect_result(Collected *c)
{
    PyObject *r = PyTuple_Pack(6, c->arr[O_OBS], c->arr[O_REW], c->arr[O_TERM], c->trunc,
                               c->cols, c->info ? c->info : Py_None);
    collect_clear(c);
    return r;
}

/* An int64 (n,) or bool (n,) buffer of a vector env, writable or not; -1 with an error set. */
static int vec_buffer(PyObject *obj, Py_buffer *v, Py_ssize_t n, int boolean, int writable,
                      const char *what)
{
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, v, flags) < 0)
        return -1;
    const char *f = v->format;
    int ok = boolean ? (v->len == n && f != NULL && strcmp(f, "?") == 0)
                     : (v->itemsize == 8 && v->len == n * 8 && f != NULL &&
                        (strcmp(f, "q") == 0 || strcmp(f, "l") == 0));
    if (!ok) {
        PyBuffer_Release(v);
        PyErr_Format(PyExc_ValueError, "%s must be %s of shape (%zd,)", what,
                     boolean ? "bool" : "int64", n);
        return -1;
    }
    return 0;
}

/* The arguments collect() and vstep() share: their count, no step running, max_steps (args[im]),
 * want_info (args[iw]) and spec (args[is], a tuple). 0, or -1 with an error set. */
static int vec_args(BatchObject *b, const char *name, PyObject *const *args, Py_ssize_t nargs,
                    int im, int iw, int is, long long *max_steps, int *want)
{
    if (nargs != 6) {
        PyErr_Format(PyExc_TypeError, "%s() takes 6 arguments", name);
        return -1;
    }
    if (!b->have_out || b->running) {
        PyErr_SetString(PyExc_RuntimeError, "step kernel: no outputs, or a step is running");
        return -1;
    }
    *max_steps = PyLong_AsLongLong(args[im]);
    if (*max_steps == -1 && PyErr_Occurred())
        return -1;
    if ((*want = PyObject_IsTrue(args[iw])) < 0)
        return -1;
    if (!PyTuple_Check(args[is])) {
        PyErr_SetString(PyExc_TypeError, "spec must be a tuple");
        return -1;
    }
    return 0;
}

static PyObject *batch_collect(BatchObject *b, PyObject *const *args, Py_ssize_t nargs)
{
    Py_ssize_t n = b->n;
    long long max_steps;
    int want;
    if (vec_args(b, "collect", args, nargs, 1, 5, 4, &max_steps, &want) < 0)
        return NULL;
    Py_buffer ev, av, rv;
    int have_a = 0, have_r = 0;
    PyObject *result = NULL;
    if (vec_buffer(args[0], &ev, n, 0, 1, "elapsed") < 0)
        return NULL;
    if (args[2] != Py_None) {
        if (vec_buffer(args[2], &av, n, 1, 0, "active") < 0)
            goto done;
        have_a = 1;
    }
    if (args[3] != Py_None) {
        if (vec_buffer(args[3], &rv, n, 1, 1, "autoreset") < 0)
            goto done;
        have_r = 1;
    }
    Collected c;
    if (collect_alloc(b, args[4], want, &c) < 0)
        goto done;
    collect_fill(b, &c, ev.buf, max_steps, have_a ? av.buf : NULL, have_r ? rv.buf : NULL, NULL);
    result = collect_result(&c);
done:
    PyBuffer_Release(&ev);
    if (have_a)
        PyBuffer_Release(&av);
    if (have_r)
        PyBuffer_Release(&rv);
    return result;
}

/* vstep(actions, elapsed, autoreset, max_steps, spec, want_info) -> (obs, rewards, terminated,
 * truncated, cols, info or None, reset slots (list) or None, any autoreset pending (bool)), or
 * None when this step needs the general path: a native vector env's whole NEXT_STEP step in one
 * call (MKVVectorEnv._step_kernel's fast path, for envs the kernel resets itself). The slots
 * flagged in autoreset are reset in C (not stepped: reward 0, not done, elapsed 0), every other
 * slot is stepped with ``actions``; then collect's bookkeeping, autoreset rewritten in place.
 * None (nothing done) when actions are not an int64 (n, 2) array, a flagged slot cannot be reset
 * in C, or a slot needs noise drawn by Python. */
static PyObject *batch_vstep(BatchObject *b, PyObject *const *args, Py_ssize_t nargs)
{
    Py_ssize_t n = b->n;
    long long max_steps;
    int want;
    if (vec_args(b, "vstep", args, nargs, 3, 5, 4, &max_steps, &want) < 0)
        return NULL;
    Py_buffer av, ev, rv;
    if (PyObject_GetBuffer(args[0], &av, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) {
        PyErr_Clear();
        Py_RETURN_NONE;
    }
    if (av.itemsize != 8 || av.len != n * 16 || av.format == NULL ||
        (strcmp(av.format, "q") != 0 && strcmp(av.format, "l") != 0) || av.ndim != 2 ||
        av.shape == NULL || av.shape[0] != n || av.shape[1] != 2) {
        PyBuffer_Release(&av);
        Py_RETURN_NONE;
    }
    if (vec_buffer(args[1], &ev, n, 0, 1, "elapsed") < 0) {
        PyBuffer_Release(&av);
        return NULL;
    }
    if (vec_buffer(args[2], &rv, n, 1, 1, "autoreset") < 0) {
        PyBuffer_Release(&av);
        PyBuffer_Release(&ev);
        return NULL;
    }
    PyObject *result = Py_None, *resets = Py_None, *out = NULL;
    Py_INCREF(Py_None);
    Py_INCREF(Py_None);
    const int64_t *a = av.buf;
    uint8_t *ar = rv.buf;
    int any = 0;
    for (Py_ssize_t i = 0; i < n; i++)
        if (ar[i]) {
            any = 1;
            if (!b->reset_ready || b->slots[i].gen == NULL)
                goto release; /* Python resets it: the general path */
        }
    for (Py_ssize_t i = 0; i < 2 * n; i++)
        if (a[i] < 0 || a[i] > 2) {
            PyErr_Format(PyExc_ValueError, "action value %lld out of {0, 1, 2}", (long long)a[i]);
            goto fail;
        }
    for (Py_ssize_t i = 0; i < n; i++) {
        if (ar[i])
            continue;
        if (b->slots[i].body == NULL) {
            PyErr_Format(PyExc_RuntimeError, "step kernel slot %zd has no world: call reset()", i);
            goto fail;
        }
        if (needs_noise(&b->slots[i]))
            goto release;
    }
    if (any) {
        if (b->scratch == NULL && (b->scratch = malloc((size_t)(n > 0 ? n : 1))) == NULL) {
            PyErr_NoMemory();
            goto fail;
        }
        for (Py_ssize_t i = 0; i < n; i++)
            b->scratch[i] = !ar[i];
        Py_CLEAR(resets);
        for (Py_ssize_t i = 0; i < n; i++)
            if (ar[i] && append_index(&resets, i) < 0)
                goto fail;
    }
    if (start_workers(b) < 0)
        goto fail;
    b->acts = a;
    b->active = any ? b->scratch : NULL;
    b->resets = any ? ar : NULL;
    b->job_have_mask = b->job_have_reset = 0;
    /* the workers start; this thread makes the result arrays meanwhile, then joins them */
    launch_job(b);
    Collected c;
    int made = collect_alloc(b, args[4], want, &c);
    Py_BEGIN_ALLOW_THREADS
    finish_job(b);
    Py_END_ALLOW_THREADS
    const uint8_t *active = b->active;
    PyObject *err = conclude_job(b); /* (clears acts/active/resets; releases nothing of ours) */
    if (err == NULL || made < 0) {
        Py_XDECREF(err);
        if (made == 0)
            collect_clear(&c);
        goto fail;
    }
    Py_DECREF(err);
    collect_fill(b, &c, ev.buf, max_steps, active, ar, any ? ar : NULL);
    out = collect_result(&c);
    if (out == NULL)
        goto fail;
    /* collect_fill rewrote ar (the flags for the next step); the slots reset this step are in
     * ``resets`` */
    int pending = 0;
    for (Py_ssize_t i = 0; i < n; i++)
        pending |= ar[i];
    Py_DECREF(result);
    result = Py_BuildValue("(OOOOOOOO)", PyTuple_GET_ITEM(out, 0), PyTuple_GET_ITEM(out, 1),
                           PyTuple_GET_ITEM(out, 2), PyTuple_GET_ITEM(out, 3),
                           PyTuple_GET_ITEM(out, 4), PyTuple_GET_ITEM(out, 5), resets,
                           pending ? Py_True : Py_False);
    Py_DECREF(out);
    goto release;
fail:
    Py_CLEAR(result);
release:
    Py_XDECREF(resets);
    PyBuffer_Release(&av);
    PyBuffer_Release(&ev);
    PyBuffer_Release(&rv);
    return result;
}
#endif

/* physics(actions, active) -> None: only the physics of every active robot (the floor the
 * benchmark compares against); sensors, tracker and outputs untouched. */
static PyObject *batch_physics(BatchObject *b, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer av;
    if (nargs != 1) {
        PyErr_SetString(PyExc_TypeError, "physics() takes 1 argument");
        return NULL;
    }
    if (PyObject_GetBuffer(args[0], &av, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0)
        return NULL;
    if (av.itemsize != 8 || av.len != b->n * 16) {
        PyBuffer_Release(&av);
        PyErr_Format(PyExc_ValueError, "actions must be int64 of shape (%zd, 2)", b->n);
        return NULL;
    }
    const int64_t *a = av.buf;
    for (Py_ssize_t i = 0; i < b->n; i++) {
        Slot *s = &b->slots[i];
        if (s->body == NULL)
            continue;
        advance_one(b->K, s->body, s->space, (long)(a[2 * i] - 1), (long)(1 - a[2 * i + 1]),
                    b->P[P_DT], (long)b->P[P_SUBSTEPS], s->v[V_MU], s->v, 1);
    }
    PyBuffer_Release(&av);
    Py_RETURN_NONE;
}

static PyObject *batch_get_n(BatchObject *b, void *closure) { return PyLong_FromSsize_t(b->n); }
static PyObject *batch_get_threads(BatchObject *b, void *closure)
{
    return PyLong_FromLong(b->nthreads);
}

static PyObject *batch_set_reset(BatchObject *b, PyObject *const *args, Py_ssize_t nargs);
static PyObject *batch_can_reset(BatchObject *b, PyObject *idx);
static PyObject *batch_adopt(BatchObject *b, PyObject *const *args, Py_ssize_t nargs);

static PyMethodDef batch_methods[] = {
    {"set_reset", (PyCFunction)(void (*)(void))batch_set_reset, METH_FASTCALL,
     "set_reset(R, layout_constants): the constants of resets in C (MKV-v0, MKV-v1)."},
    {"can_reset", (PyCFunction)batch_can_reset, METH_O,
     "can_reset(i) -> True when a step may reset slot i in C."},
    {"adopt", (PyCFunction)(void (*)(void))batch_adopt, METH_FASTCALL,
     "adopt(i, counts) -> the world slot i built (pointers, layout, start), or None."},
    {"outputs", (PyCFunction)(void (*)(void))batch_outputs, METH_FASTCALL,
     "outputs(obs, rew, term, stuck, bumped, collision, distance, jams, escapes, collisions, "
     "in_jam, pose, cells, escaped): the buffers every step writes."},
    {"bind", (PyCFunction)(void (*)(void))batch_bind, METH_FASTCALL,
     "bind(i, body_ptr, space_ptr, counts, patches): slot i steps this world."},
    {"load", (PyCFunction)(void (*)(void))batch_load, METH_FASTCALL,
     "load(i, values, row, cells): slot i's state (see mkv_env.kernel)."},
    {"set_params", (PyCFunction)batch_set_params, METH_O,
     "set_params(params): the env's reward weights and thresholds, anew."},
    {"set_noise", (PyCFunction)(void (*)(void))batch_set_noise, METH_FASTCALL,
     "set_noise(i, block): a new 256 x 10 block of sensor noise for slot i."},
    {"state", (PyCFunction)batch_state, METH_O, "state(i) -> (values, row, noise, cells)."},
#ifdef MKV_NUMPY
    {"vstep", (PyCFunction)(void (*)(void))batch_vstep, METH_FASTCALL,
     "vstep(actions, elapsed, autoreset, max_steps, spec, want_info) -> a vector env's whole "
     "step (resets in C included), or None when it needs the general path."},
    {"collect", (PyCFunction)(void (*)(void))batch_collect, METH_FASTCALL,
     "collect(elapsed, max_steps, active, autoreset, spec, want_info) -> (obs, rewards, "
     "terminated, truncated, cols, info): a vector env's bookkeeping after step()."},
#endif
    {"set_noise_source", (PyCFunction)(void (*)(void))batch_set_noise_source, METH_FASTCALL,
     "set_noise_source(i, bit_generator, std, bias) -> True when slot i draws its own noise."},
    {"read", (PyCFunction)batch_read, METH_O,
     "read(i) -> True, or False when slot i needs noise first: a reset's observation."},
    {"step1", (PyCFunction)(void (*)(void))batch_step1, METH_FASTCALL,
     "step1(i, drive, steer) -> info tuple, or None when slot i needs noise first."},
    {"step", (PyCFunction)(void (*)(void))batch_step, METH_FASTCALL,
     "step(actions, active[, resets]) -> None, or the slots that need noise first."},
    {"step_start", (PyCFunction)(void (*)(void))batch_step_start, METH_FASTCALL,
     "step_start(actions, active[, resets]) -> None, or the slots that need noise first."},
    {"step_finish", (PyCFunction)batch_step_finish, METH_NOARGS,
     "step_finish(): join the started step and wait for its end."},
    {"physics", (PyCFunction)(void (*)(void))batch_physics, METH_FASTCALL,
     "physics(actions): the physics alone of every bound robot (benchmark floor)."},
    {NULL, NULL, 0, NULL}};

static PyGetSetDef batch_getset[] = {
    {"n", (getter)batch_get_n, NULL, "number of slots", NULL},
    {"num_threads", (getter)batch_get_threads, NULL, "threads stepping the batch", NULL},
    {NULL, NULL, NULL, NULL, NULL}};

static PyTypeObject BatchType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "mkv_env._fastsim.Batch",
    .tp_basicsize = sizeof(BatchObject),
    .tp_dealloc = (destructor)batch_dealloc,
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Batch(n, K, params, sensor_constants, num_threads): the step kernel's N slots.",
    .tp_methods = batch_methods,
    .tp_getset = batch_getset,
    .tp_new = batch_new,
};

/* bind_kernel(get_position, point_query_nearest, arbiter_get_shapes, shape_get_collision_type)
 * -> (contact_begin address, contact_separate address) */
static PyObject *fs_bind_kernel(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    void *p[4];
    if (nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "bind_kernel() takes 4 arguments");
        return NULL;
    }
    if (get_pointers(args, 4, p) < 0)
        return NULL;
    cp_get_p = (get_vect_fn)p[0];
    cp_pq = (pq_fn)p[1];
    cp_arb_shapes = (arb_shapes_fn)p[2];
    cp_shape_type = (shape_type_fn)p[3];
    return Py_BuildValue("(NN)", PyLong_FromVoidPtr((void *)contact_begin),
                         PyLong_FromVoidPtr((void *)contact_separate));
}

/* hypot(a, b[, variant]): the C copy of math.hypot the kernel uses (tests compare the two);
 * variant (0 or 1) also becomes the kernel's when given. */
static PyObject *fs_hypot(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 2 && nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "hypot() takes 2 or 3 arguments");
        return NULL;
    }
    double a = PyFloat_AsDouble(args[0]), b = PyFloat_AsDouble(args[1]);
    long variant = nargs == 3 ? PyLong_AsLong(args[2]) : hypot_variant;
    if (PyErr_Occurred())
        return NULL;
    if (variant != 0 && variant != 1) {
        PyErr_SetString(PyExc_ValueError, "variant must be 0 or 1");
        return NULL;
    }
    hypot_variant = (int)variant;
    return PyFloat_FromDouble(py_hypot(a, b));
}

static PyObject *fs_pymod(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "pymod() takes 2 arguments");
        return NULL;
    }
    double a = PyFloat_AsDouble(args[0]), b = PyFloat_AsDouble(args[1]);
    if (PyErr_Occurred())
        return NULL;
    return PyFloat_FromDouble(py_mod(a, b));
}


/* ============================================================================ arena layouts
 * generate_layout(bitgen_capsule, W, H, n_clutter, n_patches, patch_scale, reserved, consts)
 * mkv_env.world.generate_layout in C: the same draws from the same numpy bit generator
 * (Generator.random() is next_double of its bit generator; uniform(a, b) = a + (b - a) * u), the
 * same geometry and the same rejections, so the same layout to the bit. consts (float64):
 * margin, tries, box lo/hi, cylinder lo/hi, wall piece lo/hi, corner arm lo/hi, dead-end gap
 * lo/hi, dead-end depth lo/hi, clutter gap lo/hi, patch side lo/hi, wall radius, then the 5
 * cumulative kind probabilities (box, cylinder, wall, corner, dead end).
 * Returns (boxes, cylinders, walls, patches): lists of float tuples (walls without the arena's). */
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

/* The layout's obstacles into C arrays (each appended after those already there): walls (4
 * numbers), boxes (5), cylinders (3), patches (5). */
typedef struct {
    double *walls, *boxes, *cyls, *patches;
    long nw, nb, nc, np;
} LayoutOut;

/* generate_layout's draws and geometry. circles: the nc reserved circles, with room for
 * 3 * n_clutter more. */
static void layout_core(np_bitgen *g, double W, double H, long n_clutter, long n_patches,
                        double patch_scale, circle *circles, Py_ssize_t nc, const double *L,
                        LayoutOut *o)
{
    const double m = L[L_MARGIN], wr = L[L_WALL_R];
    const long tries = (long)L[L_TRIES];
    for (long item = 0; item < n_clutter; item++) {
        for (long attempt = 0; attempt < tries; attempt++) {
            double u = g->next_double(g->state);
            int kind = 0;
            while (kind < 4 && !(u < L[L_CDF + kind])) /* bisect_right over the cdf */
                kind++;
            double cx = uni(g, m, W - m);
            double cy = uni(g, m, H - m);
            double ang = uni(g, -M_PI, M_PI);
            double spec[3][5];
            circle b[3];
            int ni = 0, is_wall = 1;
            if (kind == 0) {
                double w = uni(g, L[L_BOX0], L[L_BOX1]);
                double h = uni(g, L[L_BOX0], L[L_BOX1]);
                spec[0][0] = cx; spec[0][1] = cy; spec[0][2] = w; spec[0][3] = h; spec[0][4] = ang;
                b[0].x = cx; b[0].y = cy; b[0].r = 0.5 * py_hypot(w, h);
                ni = 1;
                is_wall = 0;
            } else if (kind == 1) {
                double r = uni(g, L[L_CYL0], L[L_CYL1]);
                spec[0][0] = cx; spec[0][1] = cy; spec[0][2] = r;
                b[0].x = cx; b[0].y = cy; b[0].r = r;
                ni = 1;
                is_wall = 0;
            } else if (kind == 2) {
                double half = 0.5 * uni(g, L[L_WALL0], L[L_WALL1]);
                double dx = half * cos(ang), dy = half * sin(ang);
                spec[0][0] = cx - dx; spec[0][1] = cy - dy; spec[0][2] = cx + dx; spec[0][3] = cy + dy;
                ni = 1;
            } else if (kind == 3) {
                double la = uni(g, L[L_ARM0], L[L_ARM1]);
                double lb = uni(g, L[L_ARM0], L[L_ARM1]);
                double ex = cx + la * cos(ang), ey = cy + la * sin(ang);
                double fx = cx - lb * sin(ang), fy = cy + lb * cos(ang);
                spec[0][0] = cx; spec[0][1] = cy; spec[0][2] = ex; spec[0][3] = ey;
                spec[1][0] = cx; spec[1][1] = cy; spec[1][2] = fx; spec[1][3] = fy;
                ni = 2;
            } else {
                double gap = uni(g, L[L_GAP0], L[L_GAP1]);
                double depth = uni(g, L[L_DEPTH0], L[L_DEPTH1]);
                /* mkv_env.world.dead_end_walls */
                double c = cos(ang), s = sin(ang);
                double half = 0.5 * gap + wr;
                double blx = cx + c * 0.0 - s * half, bly = cy + s * 0.0 + c * half;
                double brx = cx + c * 0.0 - s * -half, bry = cy + s * 0.0 + c * -half;
                double olx = cx + c * depth - s * half, oly = cy + s * depth + c * half;
                double orx = cx + c * depth - s * -half, ory = cy + s * depth + c * -half;
                double segs[3][4] = {{blx, bly, brx, bry}, {blx, bly, olx, oly},
                                     {brx, bry, orx, ory}};
                for (int j = 0; j < 3; j++)
                    memcpy(spec[j], segs[j], sizeof segs[j]);
                ni = 3;
            }
            if (is_wall)
                for (int j = 0; j < ni; j++)
                    bounding_wall(spec[j], wr, &b[j]);
            int inside = 1;
            for (int j = 0; j < ni && inside; j++)
                inside = b[j].r < b[j].x && b[j].x < W - b[j].r && b[j].r < b[j].y &&
                         b[j].y < H - b[j].r;
            if (!inside)
                continue;
            double cgap = uni(g, L[L_CGAP0], L[L_CGAP1]);
            int hit = 0;
            for (int j = 0; j < ni && !hit; j++)
                for (Py_ssize_t k = 0; k < nc && !hit; k++)
                    hit = near(b[j].x - circles[k].x, b[j].y - circles[k].y,
                               b[j].r + circles[k].r + cgap);
            if (hit)
                continue;
            for (int j = 0; j < ni; j++) {
                if (kind == 0)
                    memcpy(o->boxes + 5 * o->nb++, spec[j], 5 * sizeof(double));
                else if (kind == 1)
                    memcpy(o->cyls + 3 * o->nc++, spec[j], 3 * sizeof(double));
                else
                    memcpy(o->walls + 4 * o->nw++, spec[j], 4 * sizeof(double));
                circles[nc++] = b[j];
            }
            break;
        }
    }
    for (long k = 0; k < n_patches; k++) {
        double pw = uni(g, L[L_PATCH0], L[L_PATCH1]);
        double ph = uni(g, L[L_PATCH0], L[L_PATCH1]);
        double x0 = uni(g, 0, W - pw);
        double y0 = uni(g, 0, H - ph);
        double *p = o->patches + 5 * o->np++;
        p[0] = x0; p[1] = y0; p[2] = x0 + pw; p[3] = y0 + ph; p[4] = patch_scale;
    }
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

static PyObject *fs_generate_layout(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 8) {
        PyErr_SetString(PyExc_TypeError, "generate_layout() takes 8 arguments");
        return NULL;
    }
    np_bitgen *g = PyCapsule_GetPointer(args[0], "BitGenerator");
    if (g == NULL)
        return NULL;
    double W = PyFloat_AsDouble(args[1]), H = PyFloat_AsDouble(args[2]);
    long n_clutter = PyLong_AsLong(args[3]), n_patches = PyLong_AsLong(args[4]);
    double patch_scale = PyFloat_AsDouble(args[5]);
    if (PyErr_Occurred())
        return NULL;
    if (n_clutter < 0)
        n_clutter = 0;
    if (n_patches < 0)
        n_patches = 0;
    double L[L_LEN];
    if (get_doubles(args[7], L, L_LEN, "layout constants") < 0)
        return NULL;
    PyObject *res = PySequence_Fast(args[6], "reserved must be a sequence");
    if (res == NULL)
        return NULL;
    Py_ssize_t nres = PySequence_Fast_GET_SIZE(res);
    Py_ssize_t cap = nres + 3 * n_clutter + 4;
    circle *circles = PyMem_Malloc((size_t)cap * sizeof(circle));
    size_t nd = (size_t)(12 * n_clutter + 5 * n_clutter + 3 * n_clutter + 5 * n_patches + 1);
    double *buf = PyMem_Malloc(nd * sizeof(double));
    PyObject *boxes = NULL, *cyls = NULL, *walls = NULL, *patches = NULL, *out = NULL;
    if (circles == NULL || buf == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    Py_ssize_t nc = 0;
    for (Py_ssize_t k = 0; k < nres; k++) {
        if (!PyArg_ParseTuple(PySequence_Fast_GET_ITEM(res, k), "ddd", &circles[nc].x,
                              &circles[nc].y, &circles[nc].r))
            goto done;
        nc++;
    }
    LayoutOut o = {buf, buf + 12 * n_clutter, buf + 17 * n_clutter, buf + 20 * n_clutter,
                   0, 0, 0, 0};
    layout_core(g, W, H, n_clutter, n_patches, patch_scale, circles, nc, L, &o);
    boxes = tuples_of(o.boxes, o.nb, 5);
    cyls = tuples_of(o.cyls, o.nc, 3);
    walls = tuples_of(o.walls, o.nw, 4);
    patches = tuples_of(o.patches, o.np, 5);
    if (boxes && cyls && walls && patches)
        out = PyTuple_Pack(4, boxes, cyls, walls, patches);
done:
    PyMem_Free(circles);
    PyMem_Free(buf);
    Py_DECREF(res);
    Py_XDECREF(boxes);
    Py_XDECREF(cyls);
    Py_XDECREF(walls);
    Py_XDECREF(patches);
    return out;
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


/* ============================================================================ static arenas
 * The layout's obstacles as raw Chipmunk shapes (no pymunk wrappers: the step kernel's worlds
 * build theirs ~10x faster), made exactly as mkv_env.world.add_obstacles makes them through
 * pymunk: same constructors, same arguments, same order, on the pymunk space's static body. */
typedef struct { double a, b, c, d, tx, ty; } cpXform;
typedef void *(*seg_new_fn)(void *, cpVect, cpVect, double);
typedef void *(*poly_new_fn)(void *, int, cpVect *, cpXform, double);
typedef void *(*circle_new_fn)(void *, double, cpVect);
typedef void (*shape_set_u_fn)(void *, uintptr_t);
typedef void (*shape_set_d_fn)(void *, double);
typedef void *(*space_add_shape_fn)(void *, void *);
typedef void (*space_remove_shape_fn)(void *, void *);
typedef void *(*shape_get_ptr_fn)(void *);
typedef void (*shape_free_fn)(void *);
typedef void (*shape_query_cb)(void *, void *, void *);
typedef unsigned char (*space_shape_query_fn)(void *, void *, shape_query_cb, void *);
typedef void (*shape_set_hashid_fn)(void *, uintptr_t);

static seg_new_fn cp_seg_new;
static poly_new_fn cp_poly_new;
static circle_new_fn cp_circle_new;
static shape_set_u_fn cp_shape_set_type, cp_shape_set_hashid;
static shape_set_d_fn cp_shape_set_friction, cp_shape_set_elasticity;
static space_add_shape_fn cp_space_add_shape;
static space_remove_shape_fn cp_space_remove_shape;
static shape_get_ptr_fn cp_shape_get_space, cp_shape_get_body;
static shape_free_fn cp_shape_free;
static space_shape_query_fn cp_space_shape_query;

typedef struct {
    Py_ssize_t n;
    void *shapes[];
} StaticShapes;

static void static_free(PyObject *cap)
{
    StaticShapes *ss = PyCapsule_GetPointer(cap, "mkv_env.static_shapes");
    if (ss == NULL) {
        PyErr_Clear();
        return;
    }
    for (Py_ssize_t k = 0; k < ss->n; k++) {
        void *sp = cp_shape_get_space(ss->shapes[k]);
        if (sp != NULL) /* the space still holds it (else a dying space or body let it go) */
            cp_space_remove_shape(sp, ss->shapes[k]);
        cp_shape_free(ss->shapes[k]);
    }
    PyMem_Free(ss);
}

/* Store Chipmunk function addresses (Python ints) into the function pointers ``slots``. */
static PyObject *bind_table(PyObject *const *args, Py_ssize_t nargs, void **slots[], int count,
                            const char *name)
{
    void *p[32];
    if (nargs != count || count > 32) {
        PyErr_Format(PyExc_TypeError, "%s() takes %d arguments", name, count);
        return NULL;
    }
    if (get_pointers(args, count, p) < 0)
        return NULL;
    for (int k = 0; k < count; k++)
        *slots[k] = p[k];
    Py_RETURN_NONE;
}

/* bind_shapes(13 Chipmunk function addresses, in this order) */
static PyObject *fs_bind_shapes(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    void **slots[] = {
        (void **)&cp_seg_new, (void **)&cp_poly_new, (void **)&cp_circle_new,
        (void **)&cp_shape_set_type, (void **)&cp_shape_set_friction,
        (void **)&cp_shape_set_elasticity, (void **)&cp_space_add_shape,
        (void **)&cp_space_remove_shape, (void **)&cp_shape_get_space, (void **)&cp_shape_free,
        (void **)&cp_shape_get_body, (void **)&cp_space_shape_query,
        (void **)&cp_shape_set_hashid};
    return bind_table(args, nargs, slots, 13, "bind_shapes");
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

/* One obstacle as add_static makes it: j = 0 wall (ax, ay, bx, by), 1 box (cx, cy, w, h, angle),
 * 2 cylinder (cx, cy, r). */
static void *static_shape(int j, const double *v, void *body, double wr)
{
    if (j == 0) { /* pymunk.Segment(sb, (ax, ay), (bx, by), WALL_RADIUS_M) */
        cpVect a = {v[0], v[1]}, b = {v[2], v[3]};
        return cp_seg_new(body, a, b, wr);
    }
    if (j == 1) { /* pymunk.Poly(sb, verts, transform=translation.rotated) */
        double cx = v[0], cy = v[1], w = v[2], h = v[3], ang = v[4];
        /* Transform(tx=cx, ty=cy) @ Transform.rotation(ang), pymunk's arithmetic */
        double c = cos(ang), s = sin(ang), ms = -s;
        cpXform t = {1.0 * c + 0.0 * s + cx * 0, 0.0 * c + 1.0 * s + cy * 0,
                     1.0 * ms + 0.0 * c + cx * 0, 0.0 * ms + 1.0 * c + cy * 0,
                     1.0 * 0.0 + 0.0 * 0.0 + cx * 1, 0.0 * 0.0 + 1.0 * 0.0 + cy * 1};
        cpVect verts[4] = {{-w / 2, -h / 2}, {w / 2, -h / 2}, {w / 2, h / 2}, {-w / 2, h / 2}};
        return cp_poly_new(body, 4, verts, t, 0.0);
    }
    cpVect off = {v[0], v[1]}; /* pymunk.Circle(sb, r, (cx, cy)) */
    return cp_circle_new(body, v[2], off);
}

/* add_static(space, static_body, walls, boxes, cylinders, consts(wall_r, friction, elasticity,
 *            collision_type, first_hashid)) -> capsule owning the shapes. first_hashid >= 0
 * gives the shapes the hash ids first_hashid, first_hashid + 1, ... (a pickled world's). */
static PyObject *fs_add_static(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 6) {
        PyErr_SetString(PyExc_TypeError, "add_static() takes 6 arguments");
        return NULL;
    }
    if (cp_seg_new == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "bind_shapes() has not been called");
        return NULL;
    }
    void *space = PyLong_AsVoidPtr(args[0]), *body = PyLong_AsVoidPtr(args[1]);
    double C[5];
    if (PyErr_Occurred() || get_doubles(args[5], C, 5, "static constants") < 0)
        return NULL;
    PyObject *lists[3] = {NULL, NULL, NULL};
    const char *what[3] = {"walls", "boxes", "cylinders"};
    Py_ssize_t total = 0;
    for (int j = 0; j < 3; j++) {
        lists[j] = PySequence_Fast(args[2 + j], what[j]);
        if (lists[j] == NULL)
            goto fail_lists;
        total += PySequence_Fast_GET_SIZE(lists[j]);
    }
    StaticShapes *ss = PyMem_Malloc(sizeof(StaticShapes) + (size_t)(total ? total : 1) * sizeof(void *));
    if (ss == NULL) {
        PyErr_NoMemory();
        goto fail_lists;
    }
    ss->n = 0;
    PyObject *cap = PyCapsule_New(ss, "mkv_env.static_shapes", static_free);
    if (cap == NULL) {
        PyMem_Free(ss);
        goto fail_lists;
    }
    const double wr = C[0];
    for (int j = 0; j < 3; j++) {
        for (Py_ssize_t k = 0; k < PySequence_Fast_GET_SIZE(lists[j]); k++) {
            PyObject *item = PySequence_Fast_GET_ITEM(lists[j], k);
            double v[5];
            if (tuple_doubles(item, v, j == 0 ? 4 : j == 1 ? 5 : 3) < 0)
                goto fail_cap;
            void *shape = static_shape(j, v, body, wr);
            if (shape == NULL) {
                PyErr_NoMemory();
                goto fail_cap;
            }
            ss->shapes[ss->n++] = shape;
        }
    }
    for (Py_ssize_t k = 0; k < ss->n; k++) {
        cp_shape_set_type(ss->shapes[k], (uintptr_t)C[3]);
        cp_shape_set_friction(ss->shapes[k], C[1]);
        cp_shape_set_elasticity(ss->shapes[k], C[2]);
    }
    for (Py_ssize_t k = 0; k < ss->n; k++) {
        cp_space_add_shape(space, ss->shapes[k]);
        if (C[4] >= 0)
            cp_shape_set_hashid(ss->shapes[k], (uintptr_t)C[4] + (uintptr_t)k);
    }
    for (int j = 0; j < 3; j++)
        Py_DECREF(lists[j]);
    return cap;
fail_cap:
    Py_DECREF(cap); /* frees the shapes made so far (none is in the space yet) */
fail_lists:
    for (int j = 0; j < 3; j++)
        Py_XDECREF(lists[j]);
    return NULL;
}

/* static_release(capsule) -> list of the shapes' addresses; the capsule no longer owns them
 * (mkv_env.kernel.adopt_static hands them to pymunk, which frees them from then on). */
static PyObject *fs_static_release(PyObject *self, PyObject *cap)
{
    StaticShapes *ss = PyCapsule_GetPointer(cap, "mkv_env.static_shapes");
    if (ss == NULL)
        return NULL;
    PyObject *out = PyList_New(ss->n);
    if (out == NULL)
        return NULL;
    for (Py_ssize_t k = 0; k < ss->n; k++) {
        PyObject *p = PyLong_FromVoidPtr(ss->shapes[k]);
        if (p == NULL) {
            Py_DECREF(out);
            return NULL;
        }
        PyList_SET_ITEM(out, k, p);
    }
    ss->n = 0;
    return out;
}

typedef struct { void *body; int hit; } overlap_data;

static void overlap_cb(void *shape, void *points, void *data)
{
    overlap_data *d = data;
    if (cp_shape_get_body(shape) != d->body)
        d->hit = 1;
}

/* overlaps(space, body, shapes) -> bool: World.robot_overlaps (any of ``shapes`` intersects a
 * shape of another body), without pymunk's query wrappers. */
static PyObject *fs_overlaps(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "overlaps() takes 3 arguments");
        return NULL;
    }
    void *space = PyLong_AsVoidPtr(args[0]);
    overlap_data d = {PyLong_AsVoidPtr(args[1]), 0};
    PyObject *f = PySequence_Fast(args[2], "shapes must be a sequence");
    if (f == NULL)
        return NULL;
    for (Py_ssize_t k = 0; k < PySequence_Fast_GET_SIZE(f) && !d.hit; k++) {
        void *shape = PyLong_AsVoidPtr(PySequence_Fast_GET_ITEM(f, k));
        if (shape == NULL)
            break;
        cp_space_shape_query(space, shape, overlap_cb, &d);
    }
    Py_DECREF(f);
    if (PyErr_Occurred())
        return NULL;
    return PyBool_FromLong(d.hit);
}


/* ---------------------------------------------------------------- resets in C */
/* A vector env's autoreset of MKV-v0 / MKV-v1 on the worker threads: MKVEnv._reset_raw for a
 * continuing episode generator, in C: the layout (generate_layout's draws), the World (the same
 * Chipmunk calls, in the same order, as World.__init__ with fast_contacts and Robot.__init__
 * make through pymunk, so the same hash ids, the same spatial index and the same bits), the
 * start pose (random_free_pose's draws and point queries, _place), the sensors' and tracker's
 * reset and the first observation. The world stays the slot's until Python asks for it
 * (Batch.adopt, mkv_env.kernel.adopt_world), which hands every object to pymunk. */
typedef void *(*space_new_fn)(void);
typedef void (*free_fn)(void *);
typedef void (*space_set_int_fn)(void *, int);
typedef void *(*body_new_fn)(double, double);
typedef void *(*body_new_static_fn)(void);
typedef void *(*space_add_body_fn)(void *, void *);
typedef void (*space_body_fn)(void *, void *);
typedef void (*shape_set_filter_fn)(void *, cpFilter);
typedef void *(*add_handler_fn)(void *, uintptr_t, uintptr_t);

static space_new_fn cp_space_new;
static free_fn cp_space_free, cp_body_free;
static space_set_int_fn cp_space_set_iterations;
static set_double_fn cp_space_set_damping, cp_body_set_angle;
static body_new_fn cp_body_new;
static body_new_static_fn cp_body_new_static;
static space_add_body_fn cp_space_add_body;
static space_body_fn cp_space_remove_body, cp_space_reindex_body;
static set_vect_fn cp_body_set_position;
static shape_set_filter_fn cp_shape_set_filter;
static add_handler_fn cp_add_handler;

/* bind_reset(14 Chipmunk function addresses, in this order) */
static PyObject *fs_bind_reset(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    void **slots[] = {
        (void **)&cp_space_new, (void **)&cp_space_free, (void **)&cp_space_set_iterations,
        (void **)&cp_space_set_damping, (void **)&cp_body_new, (void **)&cp_body_new_static,
        (void **)&cp_body_free, (void **)&cp_space_add_body, (void **)&cp_space_remove_body,
        (void **)&cp_body_set_position, (void **)&cp_body_set_angle,
        (void **)&cp_shape_set_filter, (void **)&cp_space_reindex_body,
        (void **)&cp_add_handler};
    return bind_table(args, nargs, slots, 14, "bind_reset");
}

/* Free the world the slot built and still owns (a world Python adopted is pymunk's). Chipmunk
 * calls "separate" for the contacts the removals end: they count on the slot's own counts. */
static void free_cworld(Slot *s)
{
    if (!s->cworld)
        return;
    void *space = s->space;
    for (int k = 0; k < 4; k++)
        if (s->rshapes[k] != NULL) {
            if (cp_shape_get_space(s->rshapes[k]) != NULL)
                cp_space_remove_shape(space, s->rshapes[k]);
            cp_shape_free(s->rshapes[k]);
            s->rshapes[k] = NULL;
        }
    for (Py_ssize_t k = 0; k < s->nsshapes; k++) {
        if (cp_shape_get_space(s->sshapes[k]) != NULL)
            cp_space_remove_shape(space, s->sshapes[k]);
        cp_shape_free(s->sshapes[k]);
    }
    s->nsshapes = 0;
    if (s->body != NULL) {
        cp_space_remove_body(space, s->body);
        cp_body_free(s->body);
    }
    if (s->sbody != NULL) {
        cp_space_remove_body(space, s->sbody);
        cp_body_free(s->sbody);
    }
    cp_space_free(space);
    s->space = s->body = s->sbody = NULL;
    s->contacts = NULL;
    s->cworld = 0;
}

/* The arena's walls, boxes and cylinders (World with fast_contacts: add_static, then the
 * contact handlers of install_contacts), then the robot at (0, 0, 0) (Robot.__init__). */
static int build_cworld(BatchObject *b, Slot *s)
{
    const double *R = b->R;
    void *space = cp_space_new();
    if (space == NULL)
        return -1;
    s->space = space;
    s->cworld = 1;
    s->body = s->sbody = NULL;
    s->nsshapes = 0;
    cp_space_set_iterations(space, (int)R[R_ITER]);
    cp_space_set_damping(space, R[R_DAMP]);
    s->sbody = cp_body_new_static(); /* Space.static_body */
    if (s->sbody == NULL)
        return -1;
    cp_space_add_body(space, s->sbody);
    Py_ssize_t total = s->nwall + s->nbox + s->ncyl;
    if (total > s->sscap) {
        void **t = realloc(s->sshapes, (size_t)total * sizeof(void *));
        if (t == NULL)
            return -1;
        s->sshapes = t;
        s->sscap = total;
    }
    const double *lay = s->lay;
    const long counts[3] = {s->nwall, s->nbox, s->ncyl};
    const int width[3] = {4, 5, 3};
    for (int j = 0; j < 3; j++)
        for (long k = 0; k < counts[j]; k++) {
            void *shape = static_shape(j, lay, s->sbody, R[R_WALL_R]);
            lay += width[j];
            if (shape == NULL)
                return -1;
            s->sshapes[s->nsshapes++] = shape;
        }
    for (Py_ssize_t k = 0; k < s->nsshapes; k++) {
        cp_shape_set_type(s->sshapes[k], (uintptr_t)R[R_OBS_TYPE]);
        cp_shape_set_friction(s->sshapes[k], R[R_OBS_FRIC]);
        cp_shape_set_elasticity(s->sshapes[k], R[R_OBS_ELAST]);
    }
    for (Py_ssize_t k = 0; k < s->nsshapes; k++)
        cp_space_add_shape(space, s->sshapes[k]);
    memset(s->own_counts, 0, sizeof s->own_counts);
    s->contacts = s->own_counts;
    for (int k = 0; k < 4; k++) {
        char *h = cp_add_handler(space, (uintptr_t)R[R_TYPES + k], (uintptr_t)R[R_OBS_TYPE]);
        if (h == NULL)
            return -1;
        void *begin = (void *)contact_begin, *separate = (void *)contact_separate;
        void *data = s->own_counts;
        memcpy(h + (size_t)R[R_H_BEGIN], &begin, sizeof begin);
        memcpy(h + (size_t)R[R_H_SEP], &separate, sizeof separate);
        memcpy(h + (size_t)R[R_H_DATA], &data, sizeof data);
    }
    void *body = cp_body_new(R[R_MASS], R[R_MOMENT]);
    if (body == NULL)
        return -1;
    s->body = body;
    cpVect origin = {0.0, 0.0};
    cp_body_set_position(body, origin);
    cp_body_set_angle(body, 0.0);
    const double *c = R + R_CHASSIS;
    cpVect verts[4] = {{c[0], c[1]}, {c[2], c[3]}, {c[4], c[5]}, {c[6], c[7]}};
    cpXform identity = {1.0, 0.0, 0.0, 1.0, 0.0, 0.0};
    s->rshapes[0] = cp_poly_new(body, 4, verts, identity, 0.0);
    for (int k = 0; k < 3; k++) {
        const double *sg = R + R_FL + 4 * k;
        cpVect a = {sg[0], sg[1]}, e = {sg[2], sg[3]};
        s->rshapes[1 + k] = cp_seg_new(body, a, e, R[R_BUMP_R]);
    }
    cpFilter f = {(uintptr_t)R[R_GROUP], 0xffffffffu, 0xffffffffu}; /* ROBOT_FILTER */
    for (int k = 0; k < 4; k++) {
        if (s->rshapes[k] == NULL)
            return -1;
        cp_shape_set_type(s->rshapes[k], (uintptr_t)R[R_TYPES + k]);
        cp_shape_set_friction(s->rshapes[k], R[R_FRIC]);
        cp_shape_set_elasticity(s->rshapes[k], 0.0);
        cp_shape_set_filter(s->rshapes[k], f);
    }
    cp_space_add_body(space, body);
    for (int k = 0; k < 4; k++)
        cp_space_add_shape(space, s->rshapes[k]);
    return 0;
}

/* MKVEnv._reset_raw (seed None) of slot i, in C; the first observation and the reset's info
 * numbers go to row i of the outputs. Returns the slot's error code. */
static int reset_slot(BatchObject *b, Py_ssize_t i)
{
    Slot *s = &b->slots[i];
    const double *R = b->R;
    np_bitgen *g = s->gen;
    if (g == NULL || !b->reset_ready)
        return s->err = ERR_UNBOUND;
    if (s->cworld)
        free_cworld(s);
    else if (s->keep != NULL) { /* Python's world: Python frees it, and its counts */
        s->retired = s->keep;
        s->keep = NULL;
    }
    s->body = s->space = NULL;
    s->contacts = NULL;
    long nclutter = (long)R[R_NCLUTTER], npatch = (long)R[R_NPATCH];
    size_t cap = (size_t)(12 * nclutter + 5 * nclutter + 3 * nclutter + 16);
    if (cap > s->laycap) {
        double *t = realloc(s->lay, cap * sizeof(double));
        if (t == NULL)
            return s->err = ERR_MEMORY;
        s->lay = t;
        s->laycap = cap;
    }
    double *pt = realloc(s->patches, (size_t)(npatch > 0 ? npatch : 1) * 5 * sizeof(double));
    circle *circles = malloc((size_t)(3 * nclutter + 4) * sizeof(circle));
    if (pt != NULL)
        s->patches = pt;
    if (pt == NULL || circles == NULL) {
        free(circles);
        return s->err = ERR_MEMORY;
    }
    const double W = R[R_W], H = R[R_H], m = R[R_MARGIN];
    int found = 0;
    double x = 0.0, y = 0.0, th = 0.0;
    for (long attempt = 0; attempt < (long)R[R_ATTEMPTS] && !found; attempt++) {
        /* generate_layout: the arena's walls first, then the clutter */
        double *wl = s->lay;
        const double arena[16] = {0, 0, W, 0, W, 0, W, H, W, H, 0, H, 0, H, 0, 0};
        memcpy(wl, arena, sizeof arena);
        LayoutOut o = {wl + 16, wl + 16 + 12 * nclutter, wl + 16 + 17 * nclutter, s->patches,
                       0, 0, 0, 0};
        layout_core(g, W, H, nclutter, npatch, R[R_PSCALE], circles, 0, b->L, &o);
        /* pack walls, boxes, cylinders contiguously, as build_cworld reads them */
        s->nwall = 4 + o.nw;
        s->nbox = o.nb;
        s->ncyl = o.nc;
        memmove(wl + 4 * s->nwall, o.boxes, (size_t)o.nb * 5 * sizeof(double));
        memmove(wl + 4 * s->nwall + 5 * o.nb, o.cyls, (size_t)o.nc * 3 * sizeof(double));
        s->npatch = o.np;
        if (build_cworld(b, s) < 0) {
            free_cworld(s);
            free(circles);
            return s->err = ERR_MEMORY;
        }
        /* random_free_pose */
        for (long t = 0; t < (long)R[R_TRIES]; t++) {
            x = uni(g, m, W - m);
            y = uni(g, m, H - m);
            if (is_clear(s, x, y, R[R_CLEAR])) {
                th = uni(g, -M_PI, M_PI);
                found = 1;
                break;
            }
        }
        if (!found)
            free_cworld(s);
    }
    free(circles);
    if (!found)
        return s->err = ERR_NOPOSE;
    /* _place */
    cpVect p = {x, y};
    cp_body_set_position(s->body, p);
    cp_body_set_angle(s->body, th);
    cp_space_reindex_body(s->space, s->body);
    /* a new Robot's WheelState and mu, SensorSuite.reset, MotionTracker.reset (not jammed),
     * MKVEnvV1's empty cell set */
    double *v = s->v;
    memset(v, 0, sizeof s->v);
    v[V_MU] = 1.0;
    double tick = b->P[P_TICK];
    v[V_TICK_D] = floor(0.0 / tick);
    v[V_TICK_R] = floor(0.0 / tick);
    cpVect pos = cp_get_p(s->body);
    double heading = remainder(cp_get_a(s->body), 2.0 * M_PI);
    v[V_X] = v[V_JAM_X] = pos.x;
    v[V_Y] = v[V_JAM_Y] = pos.y;
    v[V_HEAD] = heading;
    v[V_EVENTS] = (double)s->contacts[0];
    s->start[0] = pos.x;
    s->start[1] = pos.y;
    s->start[2] = heading;
    cells_clear(s);
    s->row = NOISE_ROWS;
    s->err = 0;
    if (read_sensors(b, i))
        return s->err;
    /* the reset's info numbers (MKVEnv._info(False, False)) */
    const int64_t *c = s->contacts;
    OUT(b, O_REW, double)[i] = 0.0;
    OUT(b, O_TERM, uint8_t)[i] = 0;
    OUT(b, O_STUCK, uint8_t)[i] = 0;
    OUT(b, O_BUMPED, uint8_t)[i] = (uint8_t)(c[2] > 0 || c[3] > 0 || c[4] > 0);
    OUT(b, O_COLL, uint8_t)[i] = 0;
    OUT(b, O_DIST, double)[i] = v[V_DIST];
    OUT(b, O_JAMS, int64_t)[i] = 0;
    OUT(b, O_ESC, int64_t)[i] = 0;
    OUT(b, O_COLLS, int64_t)[i] = 0;
    OUT(b, O_IN_JAM, uint8_t)[i] = 0;
    double *pose = OUT(b, O_POSE, double) + 3 * i;
    pose[0] = pos.x;
    pose[1] = pos.y;
    pose[2] = heading;
    OUT(b, O_CELLS, int64_t)[i] = s->ncells;
    OUT(b, O_ESCAPED, uint8_t)[i] = 0;
    return 0;
}

/* set_reset(R (R_LEN float64), layout constants (L_LEN float64)): what a reset in C needs (see
 * mkv_env.kernel.reset_constants); only MKV-v0 and MKV-v1 envs are reset in C. */
static PyObject *batch_set_reset(BatchObject *b, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "set_reset() takes 2 arguments");
        return NULL;
    }
    if (b->running) {
        PyErr_SetString(PyExc_RuntimeError, "step kernel: a step is running");
        return NULL;
    }
    if (cp_space_new == NULL || cp_seg_new == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "bind_reset() / bind_shapes() have not been called");
        return NULL;
    }
    double R[R_LEN];
    if (get_doubles(args[0], R, R_LEN, "reset constants") < 0 ||
        get_doubles(args[1], b->L, L_LEN, "layout constants") < 0)
        return NULL;
    if (!(R[R_NCLUTTER] >= 0 && R[R_NCLUTTER] <= 100000 && R[R_NPATCH] >= 0 &&
          R[R_NPATCH] <= 100000)) {
        PyErr_SetString(PyExc_ValueError, "reset constants out of range");
        return NULL;
    }
    memcpy(b->R, R, sizeof R);
    b->reset_ready = 1;
    Py_RETURN_NONE;
}

/* can_reset(i) -> True when a job may reset slot i in C (constants set, a bit generator bound). */
static PyObject *batch_can_reset(BatchObject *b, PyObject *idx)
{
    Slot *s = get_slot(b, idx, NULL);
    if (s == NULL)
        return NULL;
    return PyBool_FromLong(b->reset_ready && s->gen != NULL);
}

/* adopt(i, counts (int64 x 5 array)) -> (space, static_body, body, robot shapes (4 addresses),
 * obstacle shapes (capsule, as add_static's), walls (after the arena's 4), boxes, cylinders,
 * patches, start pose (x, y, heading)), or None when slot i holds no world of its own: hands
 * the world the slot built to Python (mkv_env.kernel.adopt_world wraps it in pymunk objects,
 * which own and free it from then on). The contact counts move to ``counts``; the caller points
 * the contact handlers at it (install_contacts) before the next step. */
static PyObject *batch_adopt(BatchObject *b, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "adopt() takes 2 arguments");
        return NULL;
    }
    Slot *s = get_slot(b, args[0], NULL);
    if (s == NULL)
        return NULL;
    if (b->running) {
        PyErr_SetString(PyExc_RuntimeError, "step kernel: a step is running");
        return NULL;
    }
    if (!s->cworld)
        Py_RETURN_NONE;
    Py_buffer cv;
    if (PyObject_GetBuffer(args[1], &cv, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE) < 0)
        return NULL;
    int ok = cv.itemsize == 8 && cv.len == 40 && cv.format &&
             (strcmp(cv.format, "q") == 0 || strcmp(cv.format, "l") == 0);
    int64_t *counts = cv.buf;
    PyBuffer_Release(&cv); /* kept alive by s->keep, never resized (an array.array) */
    if (!ok) {
        PyErr_SetString(PyExc_ValueError, "adopt: counts must be int64 x 5");
        return NULL;
    }
    StaticShapes *ss = PyMem_Malloc(sizeof(StaticShapes) +
                                    (size_t)(s->nsshapes ? s->nsshapes : 1) * sizeof(void *));
    if (ss == NULL)
        return PyErr_NoMemory();
    ss->n = s->nsshapes;
    memcpy(ss->shapes, s->sshapes, (size_t)s->nsshapes * sizeof(void *));
    PyObject *cap = PyCapsule_New(ss, "mkv_env.static_shapes", static_free);
    if (cap == NULL) {
        PyMem_Free(ss);
        return NULL;
    }
    ss->n = 0; /* owned by the capsule only once everything below is made */
    const double *lay = s->lay;
    PyObject *walls = tuples_of(lay + 16, s->nwall - 4, 4);
    PyObject *boxes = tuples_of(lay + 4 * s->nwall, s->nbox, 5);
    PyObject *cyls = tuples_of(lay + 4 * s->nwall + 5 * s->nbox, s->ncyl, 3);
    PyObject *patches = tuples_of(s->patches, s->npatch, 5);
    PyObject *out = NULL;
    if (walls && boxes && cyls && patches)
        out = Py_BuildValue("(NNN(NNNN)OOOOO(ddd))", PyLong_FromVoidPtr(s->space),
                            PyLong_FromVoidPtr(s->sbody), PyLong_FromVoidPtr(s->body),
                            PyLong_FromVoidPtr(s->rshapes[0]), PyLong_FromVoidPtr(s->rshapes[1]),
                            PyLong_FromVoidPtr(s->rshapes[2]), PyLong_FromVoidPtr(s->rshapes[3]),
                            cap, walls, boxes, cyls, patches, s->start[0], s->start[1],
                            s->start[2]);
    Py_XDECREF(walls);
    Py_XDECREF(boxes);
    Py_XDECREF(cyls);
    Py_XDECREF(patches);
    if (out == NULL) {
        Py_DECREF(cap);
        return NULL;
    }
    ss->n = s->nsshapes;
    Py_DECREF(cap); /* out holds it */
    memcpy(counts, s->own_counts, sizeof s->own_counts);
    s->contacts = counts;
    Py_INCREF(args[1]);
    Py_XSETREF(s->keep, args[1]);
    s->nsshapes = 0;
    for (int k = 0; k < 4; k++)
        s->rshapes[k] = NULL;
    s->sbody = NULL;
    s->cworld = 0;
    return out;
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
    {"bind_kernel", (PyCFunction)(void (*)(void))fs_bind_kernel, METH_FASTCALL,
     "bind_kernel(get_p, point_query_nearest, arbiter_get_shapes, shape_get_type) -> "
     "(contact_begin, contact_separate) addresses."},
    {"drive_until_jammed", (PyCFunction)(void (*)(void))fs_drive_until_jammed, METH_FASTCALL,
     "drive_until_jammed(K, body, space, state, mu, patches, steer, dt, substeps, limit, "
     "jam_steps, max_steps, counts) -> (jammed, mu): MKVJam's start search in C."},
    {"bind_shapes", (PyCFunction)(void (*)(void))fs_bind_shapes, METH_FASTCALL,
     "bind_shapes(13 Chipmunk function addresses) for add_static and overlaps."},
    {"add_static", (PyCFunction)(void (*)(void))fs_add_static, METH_FASTCALL,
     "add_static(space, body, walls, boxes, cylinders, consts) -> capsule owning the shapes."},
    {"static_release", (PyCFunction)fs_static_release, METH_O,
     "static_release(capsule) -> the shapes' addresses, no longer owned by the capsule."},
    {"overlaps", (PyCFunction)(void (*)(void))fs_overlaps, METH_FASTCALL,
     "overlaps(space, body, shapes) -> True if a shape touches another body's."},
    {"generate_layout", (PyCFunction)(void (*)(void))fs_generate_layout, METH_FASTCALL,
     "generate_layout(bitgen, W, H, n_clutter, n_patches, patch_scale, reserved, consts): "
     "mkv_env.world.generate_layout's draws and geometry in C."},
    {"normals", (PyCFunction)(void (*)(void))fs_normals, METH_FASTCALL,
     "normals(bit_generator, k) -> k standard normals drawn in C, or None (no numpy library)."},
    {"hypot", (PyCFunction)(void (*)(void))fs_hypot, METH_FASTCALL,
     "hypot(a, b): the kernel's copy of math.hypot."},
    {"bind_reset", (PyCFunction)(void (*)(void))fs_bind_reset, METH_FASTCALL,
     "bind_reset(14 Chipmunk function addresses) for resets in C."},
    {"pymod", (PyCFunction)(void (*)(void))fs_pymod, METH_FASTCALL,
     "pymod(a, b): the kernel's copy of Python's float %."},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_fastsim",
                                    "The MK-V substep loop in C (see robot.py).", -1, methods};

PyMODINIT_FUNC PyInit__fastsim(void)
{
#ifdef MKV_NUMPY
    if (_import_array() < 0)
        return NULL;
#endif
    for (int i = 0; i < S_LEN; i++) {
        state_names[i] = PyUnicode_InternFromString(STATE_NAMES[i]);
        if (state_names[i] == NULL)
            return NULL;
    }
    PyObject *m = PyModule_Create(&module);
    if (m == NULL)
        return NULL;
    if (PyType_Ready(&BatchType) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    Py_INCREF(&BatchType);
    if (PyModule_AddObject(m, "Batch", (PyObject *)&BatchType) < 0 ||
        PyModule_AddIntConstant(m, "N_PARAMS", P_LEN) < 0 ||
        PyModule_AddIntConstant(m, "N_VALUES", V_LEN) < 0 ||
        PyModule_AddIntConstant(m, "NOISE_ROWS", NOISE_ROWS) < 0 ||
        PyModule_AddIntConstant(m, "N_CONSTANTS", K_LEN) < 0 ||
        PyModule_AddIntConstant(m, "N_RESET", R_LEN) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
