/* mkv_env._fastsim: the MK-V's wheel/motor substep loop (mkv_env.robot.Robot.advance) in C, and
 * the step kernel built on it (Batch: N robots' whole control period; see mkv_env/kernel.py).
 *
 * The same arithmetic as the Python loop in robot.py, operation for operation and in the same
 * order, so the two give the same bits: IEEE doubles, no FMA contraction (-ffp-contract=off),
 * libm's cos/sin called one by one (-fno-builtin-sin/-cos: no sincos merging), and math.hypot
 * as CPython computes it (its vector_norm, not libm's hypot) for the rare sliding branch: called
 * back in Python by advance()/advance_many(), copied in C (_native/pyfloat.c) by the kernel.
 * Chipmunk is reached through function pointers taken from pymunk's cffi module (the bind*()
 * functions), so this module links no Chipmunk library: it links libm and, when built with
 * numpy (setup.py), numpy's random library libnpyrandom (the sensor noise drawn in C).
 *
 * State in and out of advance(): the WheelState object's attributes (drive_omega, steer,
 * steer_rate, drive_angle, roller_angle, drive_budget, drive_current, steer_current).
 */
/*
 * Layout: a unity build. This file is the extension's one translation unit; the code lives in
 * mkv_env/_native/, one concern per file, #included below in dependency order, so every
 * `static` function stays file-static and the compiler sees the same code as when it was one
 * file (same flags, same bits). The _native files are not compiled on their own.
 *   abi.h           the Chipmunk ABI: re-declared types, entry-point typedefs, pointer slots
 *   kernel.h        the kernel's vectors (K_, S_, P_, V_, O_, L_, R_) and structs (Slot, Batch)
 *   pyfloat.c       CPython's float semantics: math.hypot (vector_norm), float %
 *   convert.c       Python objects <-> C arrays (WheelState, float64 buffers, tuples)
 *   wheels.c        the robot's wheel/motor substeps (advance_one), the floor friction scale
 *   bind.c          filling the Chipmunk pointer slots (bind*), contact counting callbacks
 *   robot_api.c     one-robot entry points: advance, advance_many, quantize, drive_until_jammed
 *   sensing.c       sensors, MKV-v1 cell set, tracker, rewards: one slot, one period
 *   arena.c         arena layouts (generate_layout)
 *   static_arena.c  a layout's obstacles as raw Chipmunk shapes (add_static, overlaps)
 *   threads.c       the batch's worker threads
 *   batch.c         the Batch type's life cycle and per-slot methods
 *   jobs.c          a step of the whole batch (step, step_start, step_finish, physics)
 *   vector.c        a vector env's step in one call (collect, vstep; numpy builds only)
 *   reset.c         resets in C (reset_slot, set_reset, can_reset, adopt)
 *   module.c        the CPython glue: the Batch type object, method table, PyInit__fastsim
 * scripts/c_function_lengths.py (and tests/mkv_env/test_c_layout.py) keep each file under
 * 1,000 lines and each function under 150.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <float.h>
#include <string.h>

#include <pthread.h>
#include <unistd.h>
#include <sched.h>
#include <stdatomic.h>

/* Sensor noise drawn in C: numpy's own standard normal (libnpyrandom, linked by setup.py; without
 * it the extension is not built and the envs run the Python reference) on the env's bit
 * generator, so a slot refills its noise block on whichever thread steps it, with the draws the
 * reference's SensorSuite.draw_block makes. Python draws a block (Batch.set_noise) only for a
 * slot with no generator of its own (one shared by two robots). */
#include "numpy/random/distributions.h"
/* numpy's array API (built with numpy's headers): Batch.collect makes a step's result arrays. */
#define NPY_NO_DEPRECATED_API NPY_1_7_API_VERSION
#include "numpy/arrayobject.h"

#include "_native/abi.h"
#include "_native/kernel.h"
#include "_native/pyfloat.c"
#include "_native/convert.c"
#include "_native/wheels.c"
#include "_native/bind.c"
#include "_native/robot_api.c"
#include "_native/sensing.c"
#include "_native/arena.c"
#include "_native/static_arena.c"
#include "_native/threads.c"
#include "_native/batch.c"
#include "_native/jobs.c"
#include "_native/vector.c"
#include "_native/reset.c"
#include "_native/module.c"
