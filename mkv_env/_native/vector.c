/* _native/vector.c: a vector env's step in one call (built with numpy's headers only).
 *
 * Owns: the result arrays (out_new, Collected, collect_alloc/fill/result), vec_buffer,
 * vec_args, and the methods collect and vstep.
 * Relies on: numpy's array API, kernel.h, jobs.c (append_index, conclude_job),
 * threads.c (start_workers, launch_job, finish_job), sensing.c (needs_noise). */

/* A fresh numpy array shaped like output buffer k ((n,) or (n, width)); filled later. */
static PyObject *out_new(BatchObject *b, int k)
{
    static const int types[256] = {['f'] = NPY_FLOAT32, ['d'] = NPY_FLOAT64, ['?'] = NPY_BOOL,
                                   ['q'] = NPY_INT64};
    npy_intp dims[2] = {b->n, O_WIDTH[k]};
    return PyArray_SimpleNew(O_WIDTH[k] > 1 ? 2 : 1, dims, types[(int)O_FMT[k]]);
}

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

/* collect(elapsed, max_steps, active, autoreset, spec, want_info) -> (obs, rewards, terminated,
 * truncated, cols, info or None): a vector env's per-step bookkeeping after step(), in one call
 * (MKVVectorEnv._step_kernel, the same operations as its Python fallback): fresh copies of this
 * step's outputs; elapsed (int64, n) += 1 for every stepped robot (active, bool n, or None for
 * all); truncated = elapsed >= max_steps (never when max_steps < 0) for stepped robots;
 * autoreset (bool n, or None) = terminated | truncated; cols = {name: copy of output index} for
 * each (name, mask_name, index) of spec; info = cols plus {mask_name: fresh all-True bool n}
 * when want_info (Gymnasium's vector info of robots that all report every key). */
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
