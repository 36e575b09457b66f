/* _native/pyfloat.c: CPython's float semantics in C.
 *
 * Owns: py_hypot (math.hypot = CPython's vector_norm, both the 3.10-3.11 and the 3.12+
 * variants, chosen by hypot_variant), py_mod (float %). (math.remainder is libm's remainder(),
 * called directly where the kernel needs it.)
 * Relies on: <math.h>, <float.h> only. */

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
