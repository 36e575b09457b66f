/* _native/abi.h: the Chipmunk ABI as the kernel sees it.
 *
 * Owns: the re-declared Chipmunk types (cpVect, cpPQInfo = cpPointQueryInfo, cpFilter =
 * cpShapeFilter, cpXform = cpTransform), the function-pointer typedefs of every Chipmunk entry
 * point the kernel calls, and the pointer slots themselves (NULL until bind(), bind_kernel(),
 * bind_shapes() and bind_reset() in bind.c fill them with addresses from pymunk's cffi module).
 * Relies on: <stdint.h> (uintptr_t); the struct layouts must match the Chipmunk that pymunk
 * ships (pyproject.toml requires pymunk>=7.0,<8). */
#ifndef MKV_NATIVE_ABI_H
#define MKV_NATIVE_ABI_H

typedef struct { double x, y; } cpVect;
typedef cpVect (*get_vect_fn)(const void *);
typedef double (*get_double_fn)(const void *);
typedef void (*set_vect_fn)(void *, cpVect);
typedef void (*set_double_fn)(void *, double);
typedef void (*step_fn)(void *, double);

static get_vect_fn cp_get_v = NULL;
static get_double_fn cp_get_w = NULL, cp_get_a = NULL;
static set_vect_fn cp_set_f = NULL;
static set_double_fn cp_set_t = NULL;
static step_fn cp_step = NULL;

typedef struct { const void *shape; cpVect point; double distance; cpVect gradient; } cpPQInfo;
typedef struct { uintptr_t group; unsigned int categories, mask; } cpFilter;
typedef void *(*pq_fn)(void *, cpVect, double, cpFilter, cpPQInfo *);
typedef void (*arb_shapes_fn)(void *, void **, void **);
typedef uintptr_t (*shape_type_fn)(void *);

static get_vect_fn cp_get_p = NULL;
static pq_fn cp_pq = NULL;
static arb_shapes_fn cp_arb_shapes = NULL;
static shape_type_fn cp_shape_type = NULL;

typedef struct { double a, b, c, d, tx, ty; } cpXform;
typedef void *(*seg_new_fn)(void *, cpVect, cpVect, double);
typedef void *(*poly_new_fn)(void *, int, cpVect *, cpXform, double);
typedef void *(*circle_new_fn)(void *, double, cpVect);
typedef void (*shape_set_u_fn)(void *, uintptr_t);
typedef void (*shape_set_d_fn)(void *, double);
typedef void *(*space_add_shape_fn)(void *, void *);
typedef void (*space_remove_shape_fn)(void *, void *);
typedef void *(*shape_get_ptr_fn)(void *);
typedef void (*shape_free_fn)(void *);
typedef void (*shape_query_cb)(void *, void *, void *);
typedef unsigned char (*space_shape_query_fn)(void *, void *, shape_query_cb, void *);
typedef void (*shape_set_hashid_fn)(void *, uintptr_t);

static seg_new_fn cp_seg_new;
static poly_new_fn cp_poly_new;
static circle_new_fn cp_circle_new;
static shape_set_u_fn cp_shape_set_type, cp_shape_set_hashid;
static shape_set_d_fn cp_shape_set_friction, cp_shape_set_elasticity;
static space_add_shape_fn cp_space_add_shape;
static space_remove_shape_fn cp_space_remove_shape;
static shape_get_ptr_fn cp_shape_get_space, cp_shape_get_body;
static shape_free_fn cp_shape_free;
static space_shape_query_fn cp_space_shape_query;

typedef void *(*space_new_fn)(void);
typedef void (*free_fn)(void *);
typedef void (*space_set_int_fn)(void *, int);
typedef void *(*body_new_fn)(double, double);
typedef void *(*body_new_static_fn)(void);
typedef void *(*space_add_body_fn)(void *, void *);
typedef void (*space_body_fn)(void *, void *);
typedef void (*shape_set_filter_fn)(void *, cpFilter);
typedef void *(*add_handler_fn)(void *, uintptr_t, uintptr_t);

static space_new_fn cp_space_new;
static free_fn cp_space_free, cp_body_free;
static space_set_int_fn cp_space_set_iterations;
static set_double_fn cp_space_set_damping, cp_body_set_angle;
static body_new_fn cp_body_new;
static body_new_static_fn cp_body_new_static;
static space_add_body_fn cp_space_add_body;
static space_body_fn cp_space_remove_body, cp_space_reindex_body;
static set_vect_fn cp_body_set_position;
static shape_set_filter_fn cp_shape_set_filter;
static add_handler_fn cp_add_handler;

#endif /* MKV_NATIVE_ABI_H */
