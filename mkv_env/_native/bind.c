/* _native/bind.c: filling the Chipmunk pointer slots.
 *
 * Owns: check_bound, bind() (the substep loop's entry points and math.hypot), the contact
 * callbacks contact_begin/contact_separate (World's contact counting, whose addresses
 * bind_kernel() returns), bind_kernel(), bind_table and bind_shapes()/bind_reset().
 * Relies on: abi.h (the slots), kernel.h (OBSTACLE_TYPE), convert.c (get_pointers), wheels.c
 * (py_hypot_obj). */

static int check_bound(void)
{
    if (cp_step == NULL || py_hypot_obj == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "mkv_env._fastsim: bind() has not been called");
        return -1;
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
