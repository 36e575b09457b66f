/* _native/batch.c: the Batch type's life cycle and per-slot methods.
 *
 * Owns: raise_slot_error, batch_dealloc, batch_new, get_slot, and the methods outputs, bind,
 * load, set_params, set_noise, set_noise_source (with bitgen_of), state, step1, read; and the
 * module function normals().
 * Relies on: kernel.h, convert.c (get_doubles), bind.c (check_bound), sensing.c (cells,
 * read_sensors, step_slot, needs_noise), threads.c and jobs.c (finish_job, release_job),
 * reset.c (free_cworld, declared in kernel.h). */

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

/* set_noise_source(i, bit_generator or None, std (10 float64), bias (10 float64)) -> bool: slot i
 * draws its own noise blocks from this numpy BitGenerator (the episode's SensorSuite._rng's)
 * from now on; True when bound. False (Python draws, through set_noise) for None, and for a
 * generator another slot of the batch draws from too (both then draw through Python, in slot order, as the reference does). */
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
}

/* normals(bit_generator, k) -> list of k floats from numpy's random_standard_normal in C (the
 * import-time check that the linked library draws what Generator.standard_normal draws). */
static PyObject *fs_normals(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "normals() takes 2 arguments");
        return NULL;
    }
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
