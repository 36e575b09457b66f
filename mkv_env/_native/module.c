/* _native/module.c: the CPython glue.
 *
 * Owns: the Batch type object (methods, getters), hypot() and pymod() (the kernel's copies
 * of math.hypot and float %; hypot() also sets the variant, chosen at import by
 * mkv_env.kernel), the module's method table and PyInit__fastsim.
 * Relies on: every other file (it names their functions); numpy's import_array. */

static PyObject *batch_get_n(BatchObject *b, void *closure) { return PyLong_FromSsize_t(b->n); }
static PyObject *batch_get_threads(BatchObject *b, void *closure)
{
    return PyLong_FromLong(b->nthreads);
}

/* LAYOUTS: {"K": ((name, offset, width), ...), ...} from the X-macro lists of kernel.h (names
 * without their prefix; O's entries carry the buffer format too). mkv_env/layouts.py builds
 * and reads every vector by these names. */
#define MKV_ADD_FIELD(name, width) \
    if (add_field(list, #name, (Py_ssize_t)(name), (Py_ssize_t)(width), 0) < 0) goto fail;
#define MKV_ADD_O(name, fmt, width) \
    if (add_field(list, #name, (Py_ssize_t)(name), (Py_ssize_t)(width), fmt) < 0) goto fail;

static int add_field(PyObject *list, const char *name, Py_ssize_t offset, Py_ssize_t width,
                     char fmt)
{
    const char *bare = strchr(name, '_') + 1; /* K_XD -> XD */
    PyObject *item = fmt ? Py_BuildValue("(snnC)", bare, offset, width, (int)fmt)
                         : Py_BuildValue("(snn)", bare, offset, width);
    if (item == NULL)
        return -1;
    int rc = PyList_Append(list, item);
    Py_DECREF(item);
    return rc;
}

static int add_layout(PyObject *d, const char *key, PyObject *list)
{
    PyObject *t = list ? PyList_AsTuple(list) : NULL;
    Py_XDECREF(list);
    int rc = t ? PyDict_SetItemString(d, key, t) : -1;
    Py_XDECREF(t);
    return rc;
}

static PyObject *make_layouts(void)
{
    PyObject *d = PyDict_New(), *list = NULL;
    if (d == NULL)
        return NULL;
#define MKV_LAYOUT(key, FIELDS, ADD) \
    if ((list = PyList_New(0)) == NULL) goto fail; \
    FIELDS(ADD) \
    if (add_layout(d, key, list) < 0) { list = NULL; goto fail; } \
    list = NULL;
    MKV_LAYOUT("K", K_FIELDS, MKV_ADD_FIELD)
    MKV_LAYOUT("S", S_FIELDS, MKV_ADD_FIELD)
    MKV_LAYOUT("P", P_FIELDS, MKV_ADD_FIELD)
    MKV_LAYOUT("V", V_FIELDS, MKV_ADD_FIELD)
    MKV_LAYOUT("O", O_FIELDS, MKV_ADD_O)
    MKV_LAYOUT("L", L_FIELDS, MKV_ADD_FIELD)
    MKV_LAYOUT("R", R_FIELDS, MKV_ADD_FIELD)
#undef MKV_LAYOUT
    return d;
fail:
    Py_XDECREF(list);
    Py_DECREF(d);
    return NULL;
}

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
    {"vstep", (PyCFunction)(void (*)(void))batch_vstep, METH_FASTCALL,
     "vstep(actions, elapsed, autoreset, max_steps, spec, want_info) -> a vector env's whole "
     "step (resets in C included), or None when it needs the general path."},
    {"collect", (PyCFunction)(void (*)(void))batch_collect, METH_FASTCALL,
     "collect(elapsed, max_steps, active, autoreset, spec, want_info) -> (obs, rewards, "
     "terminated, truncated, cols, info): a vector env's bookkeeping after step()."},
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

static PyMethodDef methods[] = {
    {"bind", (PyCFunction)(void (*)(void))fs_bind, METH_FASTCALL,
     "bind(get_v, get_w, get_a, set_f, set_t, step, hypot): Chipmunk entry points."},
    {"advance", (PyCFunction)(void (*)(void))fs_advance, METH_FASTCALL,
     "advance(K, body, space, drive, steer, dt, n, mu_scale, state): n substeps of one robot."},
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
    if (_import_array() < 0)
        return NULL;
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
        PyModule_AddIntConstant(m, "N_RESET", R_LEN) < 0 ||
        PyModule_AddObject(m, "LAYOUTS", make_layouts()) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
