/* _native/reset.c: resets in C.
 *
 * Owns: free_cworld, build_cworld, reset_slot (MKVEnv._reset_raw of one slot), and the methods
 * set_reset, can_reset and adopt.
 * Relies on: abi.h (the entry points bound by bind_reset and bind_shapes), kernel.h, arena.c
 * (layout_core, uni), static_arena.c (static_shape, StaticShapes), bind.c (contact_begin,
 * contact_separate), sensing.c (is_clear, read_sensors, cells_clear), batch.c (get_slot),
 * convert.c (get_doubles, tuples_of). */

/* ---------------------------------------------------------------- resets in C */
/* A vector env's autoreset of MKV-v0 / MKV-v1 on the worker threads: MKVEnv._reset_raw for a
 * continuing episode generator, in C: the layout (generate_layout's draws), the World (the same
 * Chipmunk calls, in the same order, as World.__init__ with fast_contacts and Robot.__init__
 * make through pymunk, so the same hash ids, the same spatial index and the same bits), the
 * start pose (random_free_pose's draws and point queries, _place), the sensors' and tracker's
 * reset and the first observation. The world stays the slot's until Python asks for it
 * (Batch.adopt, mkv_env.kernel.adopt_world), which hands every object to pymunk. */
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
