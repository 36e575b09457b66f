/* _native/static_arena.c: a layout's obstacles as raw Chipmunk shapes.
 *
 * Owns: StaticShapes and its capsule destructor static_free, static_shape (one obstacle),
 * add_static(), static_release(), overlaps().
 * Relies on: abi.h (the shape entry points, bound by bind_shapes), convert.c (get_doubles,
 * tuple_doubles). */

/* ============================================================================ static arenas
 * The layout's obstacles as raw Chipmunk shapes (no pymunk wrappers: the step kernel's worlds
 * build theirs ~10x faster), made exactly as mkv_env.world.add_obstacles makes them through
 * pymunk: same constructors, same arguments, same order, on the pymunk space's static body. */
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
 * (mkv_env._chipmunk.adopt_static hands them to pymunk, which frees them from then on). */
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
