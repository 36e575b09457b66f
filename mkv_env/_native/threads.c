/* _native/threads.c: the batch's worker threads.
 *
 * Owns: step_robot (reset or step one slot of the current job), run_group (the robots a thread
 * claims), the worker loop, start_workers (also after a fork), launch_job and finish_job.
 * Relies on: kernel.h (BatchObject, Worker), sensing.c (step_slot), reset.c (reset_slot,
 * declared in kernel.h), <pthread.h>, <sched.h>, <stdatomic.h>. */

/* The current job's robots, claimed one by one by the threads. Each thread has a home group, a
 * fixed contiguous share of the robots, so each robot's memory (its Chipmunk space, shapes,
 * contact buffers) mostly stays in one core's caches (threads taking robots in turn measured
 * only 1.24x on two cores, contiguous shares more; see benchmarks/env_speed.py); a thread
 * that has finished its group takes the unclaimed robots of the others (the calling thread is
 * late when it resets the envs that ended while the workers step). Which thread steps a robot
 * never changes its result: each is claimed exactly once (an atomic counter per group). */
static inline void step_robot(BatchObject *b, Py_ssize_t i)
{
    const int64_t *a = b->acts;
    if (b->resets != NULL && b->resets[i]) {
        reset_slot(b, i);
        return;
    }
    if (b->active != NULL && !b->active[i])
        return;
    /* [drive, steer] in {0,1,2}: motor commands a0 - 1 and 1 - a1 (steer 0 = left = +1) */
    step_slot(b, i, (long)(a[2 * i] - 1), (long)(1 - a[2 * i + 1]));
}

static void run_group(BatchObject *b, int g)
{
    int T = b->nthreads;
    if (T <= 1 || b->workers == NULL) {
        for (Py_ssize_t i = 0; i < b->n; i++)
            step_robot(b, i);
        return;
    }
    for (int k = 0; k < T; k++) {
        int h = (g + k) % T;
        Py_ssize_t hi = b->n * (h + 1) / T;
        atomic_long *next = &b->workers[h].next;
        for (;;) {
            Py_ssize_t i = (Py_ssize_t)atomic_fetch_add_explicit(next, 1, memory_order_relaxed);
            if (i >= hi)
                break;
            step_robot(b, i);
        }
    }
}

/* One turn of a wait loop: the first turns spin on the CPU's pause instruction (a few
 * microseconds: back-to-back steps resume at once), later ones yield the core. */
static inline void wait_a_little(int spin)
{
    if (spin < 256) {
#if defined(__x86_64__) || defined(__i386__)
        __builtin_ia32_pause();
#elif defined(__aarch64__)
        __asm__ __volatile__("yield");
#endif
    } else {
        sched_yield();
    }
}

static void *worker_main(void *arg)
{
    Worker *w = arg;
    BatchObject *b = w->b;
    long seen = 0;
    for (;;) {
        /* spin a little (back-to-back steps), then sleep on the condition variable */
        long gen = 0;
        for (int spin = 0; spin < 20000; spin++) {
            gen = __atomic_load_n(&b->gen, __ATOMIC_ACQUIRE);
            if (gen != seen || __atomic_load_n(&b->stop, __ATOMIC_ACQUIRE))
                break;
            wait_a_little(spin);
        }
        pthread_mutex_lock(&b->mu);
        while (b->gen == seen && !b->stop)
            pthread_cond_wait(&b->cv, &b->mu);
        gen = b->gen;
        int stop = b->stop;
        pthread_mutex_unlock(&b->mu);
        if (stop)
            return NULL;
        seen = gen;
        run_group(b, w->group);
        atomic_fetch_sub_explicit(&b->pending, 1, memory_order_acq_rel);
    }
}

static int start_workers(BatchObject *b)
{
    if (b->started && b->owner_pid != (long)getpid()) {
        /* a fork: this process has none of the parent's threads; start its own */
        free(b->workers);
        b->workers = NULL;
        pthread_mutex_init(&b->mu, NULL);
        pthread_cond_init(&b->cv, NULL);
        b->started = 0;
        b->gen = 0;
        b->stop = 0;
    }
    if (b->nthreads <= 1 || b->started)
        return 0;
    b->owner_pid = (long)getpid();
    b->workers = aligned_alloc(64, (size_t)b->nthreads * sizeof(Worker)); /* cursor per line */
    if (b->workers != NULL)
        memset(b->workers, 0, (size_t)b->nthreads * sizeof(Worker));
    if (b->workers == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    for (int g = 1; g < b->nthreads; g++) {
        b->workers[g].b = b;
        b->workers[g].group = g;
        if (pthread_create(&b->workers[g].th, NULL, worker_main, &b->workers[g]) != 0) {
            b->nthreads = g; /* the ones started keep working; the rest run on fewer threads */
            break;
        }
    }
    b->started = 1;
    return 0;
}

/* Hand the current job to the worker threads (they start at once). */
static void launch_job(BatchObject *b)
{
    if (b->nthreads <= 1)
        return;
    for (int g = 0; g < b->nthreads; g++) /* every group's robots unclaimed again */
        atomic_store_explicit(&b->workers[g].next, (long)(b->n * g / b->nthreads),
                              memory_order_relaxed);
    atomic_store(&b->pending, b->nthreads - 1);
    pthread_mutex_lock(&b->mu);
    __atomic_add_fetch(&b->gen, 1, __ATOMIC_RELEASE);
    pthread_cond_broadcast(&b->cv);
    pthread_mutex_unlock(&b->mu);
}

/* The calling thread joins the job, then waits for the workers (GIL released by the caller). */
static void finish_job(BatchObject *b)
{
    run_group(b, 0);
    if (b->nthreads > 1)
        for (int spin = 0; atomic_load_explicit(&b->pending, memory_order_acquire) > 0; spin++)
            wait_a_little(spin);
}
