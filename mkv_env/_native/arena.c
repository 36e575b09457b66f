/* _native/arena.c: arena layouts (mkv_env.world.generate_layout in C).
 *
 * Owns: np_bitgen (numpy's bitgen_t layout), circle, uni (Generator.uniform), bounding_wall,
 * near, LayoutOut, layout_core (the draws and geometry) and generate_layout().
 * Relies on: kernel.h (L_*), pyfloat.c (py_hypot), convert.c (get_doubles, tuples_of). */

/* ============================================================================ arena layouts
 * generate_layout(bitgen_capsule, W, H, n_clutter, n_patches, patch_scale, reserved, consts)
 * mkv_env.world.generate_layout in C: the same draws from the same numpy bit generator
 * (Generator.random() is next_double of its bit generator; uniform(a, b) = a + (b - a) * u), the
 * same geometry and the same rejections, so the same layout to the bit. consts (float64):
 * margin, tries, box lo/hi, cylinder lo/hi, wall piece lo/hi, corner arm lo/hi, dead-end gap
 * lo/hi, dead-end depth lo/hi, clutter gap lo/hi, patch side lo/hi, wall radius, then the 5
 * cumulative kind probabilities (box, cylinder, wall, corner, dead end).
 * Returns (boxes, cylinders, walls, patches): lists of float tuples (walls without the arena's). */

typedef struct {
    void *state;
    uint64_t (*next_uint64)(void *st);
    uint32_t (*next_uint32)(void *st);
    double (*next_double)(void *st);
    uint64_t (*next_raw)(void *st);
} np_bitgen;

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
