/* _native/wheels.c: the robot's wheel/motor substeps.
 *
 * Owns: advance_one (one robot, n substeps of mkv_env.robot.Robot.advance, operation for
 * operation), call_hypot and the math.hypot object it calls (bound by bind()), floor_scale
 * (World.floor_friction_scale, the friction multiplier under the drive wheel).
 * Relies on: abi.h (the Chipmunk body/space entry points), kernel.h (K_*, S_*), pyfloat.c
 * (py_hypot). */

static PyObject *py_hypot_obj = NULL;

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
