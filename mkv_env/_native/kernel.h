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

/* Layout of the constants vector K (made by mkv_env.robot.kernel_constants(params)). */
enum {
    K_XD, K_XS, K_RW, K_INV_RS, K_LIM, K_IM, K_II, K_TIRE_MU, K_N_DRIVE, K_N_STEER,
    K_S_V, K_S_K, K_S_R, K_S_J, K_S_C, K_FRIC, K_D_V, K_D_K, K_D_R, K_D_J, K_D_C,
    K_MASS, K_MOMENT, K_LEN
};
/* Layout of the state vector. */
enum { S_WW, S_DELTA, S_RATE, S_DRIVE_ANGLE, S_ROLLER_ANGLE, S_BUDGET, S_I_DRIVE, S_I_STEER, S_LEN };

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
enum {
    P_DT, P_SUBSTEPS, P_PERIOD, P_STUCK_SPEED, P_JAM_STEPS, P_ESC_DIST, P_ESC_FWD, P_FREE_CLEAR,
    P_KIND, P_PROGRESS, P_STUCK_PEN, P_COLL_PEN, P_ESC_REWARD, P_COVERAGE, P_STILL_PEN,
    P_JAM_PEN, P_TIME_PEN, P_SHAPING, P_CELL, P_TICK, P_BATT_V, P_BATT_R, P_LEN
};
enum { KIND_WANDER, KIND_JAM, KIND_WANDER_V1, KIND_JAM_V1 };
/* A slot's doubles: the wheel state (S_*, advance_one's layout) and then the rest. */
enum {
    V_MU = S_LEN, V_TICK_D, V_TICK_R, V_X, V_Y, V_HEAD, V_DIST, V_LAST, V_STUCK_RUN, V_JAMS,
    V_ESCAPES, V_IN_JAM, V_JAM_X, V_JAM_Y, V_COLLS, V_FWD, V_EVENTS, V_PHI, V_LEN
};
/* Output buffers, registered by Batch.outputs(). */
enum {
    O_OBS, O_REW, O_TERM, O_STUCK, O_BUMPED, O_COLL, O_DIST, O_JAMS, O_ESC, O_COLLS, O_IN_JAM,
    O_POSE, O_CELLS, O_ESCAPED, O_LEN
};
static const char O_FMT[O_LEN] = {'f', 'd', '?', '?', '?', '?', 'd', 'q', 'q', 'q', '?', 'd', 'q', '?'};
static const int O_WIDTH[O_LEN] = {NCH, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 3, 1, 1};

enum { ERR_NONE, ERR_NONFINITE, ERR_CELL, ERR_MEMORY, ERR_UNBOUND, ERR_NOPOSE };

enum {
    L_MARGIN, L_TRIES, L_BOX0, L_BOX1, L_CYL0, L_CYL1, L_WALL0, L_WALL1, L_ARM0, L_ARM1, L_GAP0,
    L_GAP1, L_DEPTH0, L_DEPTH1, L_CGAP0, L_CGAP1, L_PATCH0, L_PATCH1, L_WALL_R, L_CDF, L_LEN = L_CDF + 5
};

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
enum {
    R_W, R_H, R_NCLUTTER, R_NPATCH, R_PSCALE, R_WALL_R, R_OBS_FRIC, R_OBS_ELAST, R_OBS_TYPE,
    R_ITER, R_DAMP, R_MARGIN, R_CLEAR, R_TRIES, R_ATTEMPTS, R_MASS, R_MOMENT, R_FRIC,
    R_TYPES, R_CHASSIS = R_TYPES + 4, R_FL = R_CHASSIS + 8, R_FR = R_FL + 4, R_RB = R_FR + 4,
    R_BUMP_R = R_RB + 4, R_GROUP, R_H_BEGIN, R_H_SEP, R_H_DATA, R_LEN
};

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
