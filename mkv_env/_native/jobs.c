/* _native/jobs.c: a step of the whole batch.
 *
 * Owns: prepare_job (validating a job's buffers), release_job, conclude_job, and the methods
 * step, step_start, step_finish and physics.
 * Relies on: kernel.h, threads.c (start_workers, launch_job, finish_job), sensing.c
 * (needs_noise), batch.c (raise_slot_error), wheels.c (advance_one). */

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

/* step(actions (n x 2 int64, values 0..2), active (n bool) or None[, resets (n bool) or None])
 * -> None, or the list of active slots that need a new noise block first (nothing stepped then).
 * Every active robot is stepped (a slot flagged in resets is reset in C instead) with the GIL
 * released, on num_threads threads. */
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

/* step_start(actions, active[, resets]) -> None (the worker threads are stepping the active
 * robots; call step_finish() next, and touch no active slot in between), or the list of slots
 * that need noise first (nothing started). With one thread nothing runs until step_finish().
 * Inactive slots may be reset (bind, load, set_noise, read) while the workers run. */
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

/* physics(actions) -> None: only the physics of every bound robot (the floor the benchmark
 * compares against); sensors, tracker and outputs untouched. */
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
