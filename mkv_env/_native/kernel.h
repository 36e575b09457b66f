/* _native/kernel.h: the kernel's vectors and structs.
 *
 * Owns: the layouts of the constants vector K (K_*), the wheel state (S_*), a batch's
 * parameters (P_*), a slot's doubles (V_*), the output buffers (O_*), the layout constants
 * (L_*), the reset constants (R_*), the slot error codes (ERR_*); the Slot, Worker and
 * BatchObject structs; the OUT() accessor; forward declarations of the functions used before
 * their definition in the unity build (reset_slot, free_cworld, release_job).
 * Relies on: Python.h, <pthread.h>, <stdatomic.h> (included by _fastsim.c) and abi.h. */
#ifndef MKV_NATIVE_KERNEL_H
#define MKV_NATIVE_KERNEL_H

/* The layouts shared with Python, each ONE list X(name, width) from which both the enum below
 * and the extension's LAYOUTS table (module.c) are generated; Python builds and reads these
 * vectors by name through mkv_env/layouts.py, which checks the names against LAYOUTS, so a field
 * added, removed or moved here cannot silently shift the other side. An enumerator NAME_LAST_
 * marks the last index of every field (a field of width w spans NAME .. NAME + w - 1). */
#define MKV_ENUM_FIELD(name, width) name, name##_LAST_ = name + (width) - 1,

/* The constants vector K (made by mkv_env.robot.kernel_constants(params)). */
#define K_FIELDS(X) \
    X(K_XD, 1) X(K_XS, 1) X(K_RW, 1) X(K_INV_RS, 1) X(K_LIM, 1) X(K_IM, 1) X(K_II, 1) \
    X(K_TIRE_MU, 1) X(K_N_DRIVE, 1) X(K_N_STEER, 1) X(K_S_V, 1) X(K_S_K, 1) X(K_S_R, 1) \
    X(K_S_J, 1) X(K_S_C, 1) X(K_FRIC, 1) X(K_D_V, 1) X(K_D_K, 1) X(K_D_R, 1) X(K_D_J, 1) \
    X(K_D_C, 1) X(K_MASS, 1) X(K_MOMENT, 1)
enum { K_FIELDS(MKV_ENUM_FIELD) K_LEN };
/* The wheel state vector (its Python names: STATE_NAMES in convert.c, the WheelState fields). */
#define S_FIELDS(X) \
    X(S_WW, 1) X(S_DELTA, 1) X(S_RATE, 1) X(S_DRIVE_ANGLE, 1) X(S_ROLLER_ANGLE, 1) \
    X(S_BUDGET, 1) X(S_I_DRIVE, 1) X(S_I_STEER, 1)
enum { S_FIELDS(MKV_ENUM_FIELD) S_LEN };

/* ============================================================================ the step kernel
 * Batch: N robots' whole control period after the action is decoded (physics, sensors, tracker,
 * reward, termination, info numbers), each robot in a slot of C state, written into numpy
 * buffers registered once. The Python classes in envs.py, sensors.py and tracker.py are the
 * reference: every operation below is theirs, in their order, on the same doubles, so the two
 * give the same bits (tests/mkv_env/test_step_kernel.py). Nothing here calls Python, so a batch
 * steps with the GIL released and, with num_threads > 1, on worker threads (each robot has its
 * own Chipmunk space; a robot's result does not depend on which thread ran it). */

#define NCH 10
#define NOISE_ROWS 256
#define OBSTACLE_TYPE 10

/* Parameters of a batch (the env's constructor arguments), in the order of
 * mkv_env.kernel.params(env). */
#define P_FIELDS(X) \
    X(P_DT, 1) X(P_SUBSTEPS, 1) X(P_PERIOD, 1) X(P_STUCK_SPEED, 1) X(P_JAM_STEPS, 1) \
    X(P_ESC_DIST, 1) X(P_ESC_FWD, 1) X(P_FREE_CLEAR, 1) X(P_KIND, 1) X(P_PROGRESS, 1) \
    X(P_STUCK_PEN, 1) X(P_COLL_PEN, 1) X(P_ESC_REWARD, 1) X(P_COVERAGE, 1) X(P_STILL_PEN, 1) \
    X(P_JAM_PEN, 1) X(P_TIME_PEN, 1) X(P_SHAPING, 1) X(P_CELL, 1) X(P_TICK, 1) X(P_BATT_V, 1) \
    X(P_BATT_R, 1)
enum { P_FIELDS(MKV_ENUM_FIELD) P_LEN };
enum { KIND_WANDER, KIND_JAM, KIND_WANDER_V1, KIND_JAM_V1 };
/* A slot's doubles: the wheel state (S_*, advance_one's layout) and then the rest. */
#define V_FIELDS(X) \
    X(V_MU, 1) X(V_TICK_D, 1) X(V_TICK_R, 1) X(V_X, 1) X(V_Y, 1) X(V_HEAD, 1) X(V_DIST, 1) \
    X(V_LAST, 1) X(V_STUCK_RUN, 1) X(V_JAMS, 1) X(V_ESCAPES, 1) X(V_IN_JAM, 1) X(V_JAM_X, 1) \
    X(V_JAM_Y, 1) X(V_COLLS, 1) X(V_FWD, 1) X(V_EVENTS, 1) X(V_PHI, 1)
enum { V_BASE_ = S_LEN - 1, V_FIELDS(MKV_ENUM_FIELD) V_LEN };
/* Output buffers, registered by Batch.outputs(). */
/* O(name, buffer format, width per slot) */
#define O_FIELDS(O) \
    O(O_OBS, 'f', NCH) O(O_REW, 'd', 1) O(O_TERM, '?', 1) O(O_STUCK, '?', 1) \
    O(O_BUMPED, '?', 1) O(O_COLL, '?', 1) O(O_DIST, 'd', 1) O(O_JAMS, 'q', 1) O(O_ESC, 'q', 1) \
    O(O_COLLS, 'q', 1) O(O_IN_JAM, '?', 1) O(O_POSE, 'd', 3) O(O_CELLS, 'q', 1) \
    O(O_ESCAPED, '?', 1)
#define MKV_O_ENUM(name, fmt, width) name,
#define MKV_O_FMT(name, fmt, width) fmt,
#define MKV_O_WIDTH(name, fmt, width) width,
enum { O_FIELDS(MKV_O_ENUM) O_LEN };
static const char O_FMT[O_LEN] = {O_FIELDS(MKV_O_FMT)};
static const int O_WIDTH[O_LEN] = {O_FIELDS(MKV_O_WIDTH)};

enum { ERR_NONE, ERR_NONFINITE, ERR_CELL, ERR_MEMORY, ERR_UNBOUND, ERR_NOPOSE };

#define L_FIELDS(X) \
    X(L_MARGIN, 1) X(L_TRIES, 1) X(L_BOX0, 1) X(L_BOX1, 1) X(L_CYL0, 1) X(L_CYL1, 1) \
    X(L_WALL0, 1) X(L_WALL1, 1) X(L_ARM0, 1) X(L_ARM1, 1) X(L_GAP0, 1) X(L_GAP1, 1) \
    X(L_DEPTH0, 1) X(L_DEPTH1, 1) X(L_CGAP0, 1) X(L_CGAP1, 1) X(L_PATCH0, 1) X(L_PATCH1, 1) \
    X(L_WALL_R, 1) X(L_CDF, 5)
enum { L_FIELDS(MKV_ENUM_FIELD) L_LEN };

typedef struct {
    void *body, *space;
    int64_t *contacts;
    double *patches;
    Py_ssize_t npatch;
    double v[V_LEN];
    double noise[NOISE_ROWS * NCH];
    long row;
    uint64_t *cells;
    int64_t ncells, cap;
    int err;
    PyObject *keep; /* the World's counts array: kept alive while bound */
    void *gen;      /* the episode's numpy bitgen_t (noise drawn in C), or NULL */
    PyObject *gen_keep; /* its BitGenerator: kept alive while bound */
    double nstd[NCH], nbias[NCH];
    /* The world the kernel built itself at the slot's last reset (reset_slot), until Python
     * adopts it (Batch.adopt): while cworld is 1 the space, bodies and shapes are the slot's. */
    int cworld;
    void *sbody;          /* its static body */
    void *rshapes[4];     /* the robot's shapes */
    void **sshapes;       /* the obstacles' shapes */
    Py_ssize_t nsshapes, sscap;
    double *lay;          /* its layout: walls (4 numbers each), boxes (5), cylinders (3) */
    long nwall, nbox, ncyl;
    size_t laycap;
    int64_t own_counts[5]; /* its contact counts (World.contacts once adopted) */
    double start[3];      /* its start pose */
    PyObject *retired;    /* a Python world's counts array a reset let go (released under the GIL) */
} Slot;

/* A reset's constants (Batch.set_reset, from mkv_env.kernel.reset_constants): the arena, the
 * obstacles, the space, the start-pose search and the robot's body and shapes. */
#define R_FIELDS(X) \
    X(R_W, 1) X(R_H, 1) X(R_NCLUTTER, 1) X(R_NPATCH, 1) X(R_PSCALE, 1) X(R_WALL_R, 1) \
    X(R_OBS_FRIC, 1) X(R_OBS_ELAST, 1) X(R_OBS_TYPE, 1) X(R_ITER, 1) X(R_DAMP, 1) \
    X(R_MARGIN, 1) X(R_CLEAR, 1) X(R_TRIES, 1) X(R_ATTEMPTS, 1) X(R_MASS, 1) X(R_MOMENT, 1) \
    X(R_FRIC, 1) X(R_TYPES, 4) X(R_CHASSIS, 8) X(R_FL, 4) X(R_FR, 4) X(R_RB, 4) \
    X(R_BUMP_R, 1) X(R_GROUP, 1) X(R_H_BEGIN, 1) X(R_H_SEP, 1) X(R_H_DATA, 1)
enum { R_FIELDS(MKV_ENUM_FIELD) R_LEN };

typedef struct BatchObject BatchObject;

typedef struct {
    _Alignas(64) atomic_long next; /* the next robot of this group to claim (own cache line) */
    BatchObject *b;
    int group;
    pthread_t th;
} Worker;

struct BatchObject {
    PyObject_HEAD
    Py_ssize_t n;
    Slot *slots;
    double K[K_LEN], P[P_LEN];
    double iq[NCH], q[NCH], lo[NCH], hi[NCH];
    Py_buffer out[O_LEN];
    int have_out;
    /* the current job */
    const int64_t *acts;
    const uint8_t *active;
    /* threads */
    int nthreads, started;
    long owner_pid; /* the process whose threads these are (a forked child has none) */
    Worker *workers;
    pthread_mutex_t mu;
    pthread_cond_t cv;
    long gen;
    int stop;
    atomic_int pending;
    int running;       /* a job started by step_start and not yet finished */
    Py_buffer job_acts, job_mask;
    int job_have_mask;
    /* resets in C (Batch.set_reset): the env's constants, and the slots the job resets */
    double R[R_LEN], L[L_LEN];
    int reset_ready;
    const uint8_t *resets;
    Py_buffer job_reset;
    int job_have_reset;
    uint8_t *scratch; /* vstep's active mask */
    /* the last info spec (name, mask name, output index) parsed by collect_alloc, kept */
    PyObject *spec, *spec_name[O_LEN], *spec_mname[O_LEN];
    int spec_idx[O_LEN], spec_n;
};

static int reset_slot(BatchObject *b, Py_ssize_t i);
static void free_cworld(Slot *s);
static void release_job(BatchObject *b);

#define OUT(b, k, T) ((T *)(b)->out[k].buf)

#endif /* MKV_NATIVE_KERNEL_H */
