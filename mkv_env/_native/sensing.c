/* _native/sensing.c: sensing, tracking and scoring of one slot for one control period.
 *
 * Owns: the MKV-v1 cell set (cell_add, cells_clear), is_clear (a free-circle point query),
 * the sensor noise blocks (refill_noise, needs_noise), read_sensors (SensorSuite.read) and
 * step_slot (physics + sensors + MotionTracker.update + the env's reward and termination).
 * Relies on: kernel.h (Slot, BatchObject, OUT), abi.h, wheels.c (advance_one, floor_scale),
 * pyfloat.c (py_hypot, py_mod), numpy's random_standard_normal (libnpyrandom). */

/* ---------------------------------------------------------------- the cell set of MKV-v1 */
static inline uint64_t cell_hash(uint64_t k)
{
    k ^= k >> 33;
    k *= 0xff51afd7ed558ccdULL;
    k ^= k >> 33;
    return k;
}

/* 1 if the cell was new (and is now in), 0 if seen, -1 on error. */
static int cell_add(Slot *s, double cx, double cy)
{
    if (!(fabs(cx) < 2147483647.0 && fabs(cy) < 2147483647.0))
        return -1;
    uint64_t key = ((uint64_t)(uint32_t)(int32_t)cx << 32) | (uint64_t)(uint32_t)(int32_t)cy;
    key += 1; /* 0 marks an empty bucket; (uint64)-1 + 1 wraps to 0 only for (-1, -1) */
    if (key == 0)
        key = 0x8000000000000000ULL; /* unused by in-range cells (cx = INT32_MIN) */
    if ((s->ncells + 1) * 2 > s->cap) {
        int64_t cap = s->cap ? s->cap * 2 : 256;
        uint64_t *t = calloc((size_t)cap, sizeof(uint64_t));
        if (t == NULL)
            return -1;
        for (int64_t i = 0; i < s->cap; i++) {
            uint64_t k = s->cells[i];
            if (k) {
                uint64_t h = cell_hash(k) & (uint64_t)(cap - 1);
                while (t[h])
                    h = (h + 1) & (uint64_t)(cap - 1);
                t[h] = k;
            }
        }
        free(s->cells);
        s->cells = t;
        s->cap = cap;
    }
    uint64_t h = cell_hash(key) & (uint64_t)(s->cap - 1);
    while (s->cells[h]) {
        if (s->cells[h] == key)
            return 0;
        h = (h + 1) & (uint64_t)(s->cap - 1);
    }
    s->cells[h] = key;
    s->ncells += 1;
    return 1;
}

static void cells_clear(Slot *s)
{
    if (s->cells)
        memset(s->cells, 0, (size_t)s->cap * sizeof(uint64_t));
    s->ncells = 0;
}


/* ---------------------------------------------------------------- one robot, one period */

static inline int is_clear(const Slot *s, double x, double y, double radius)
{
    cpPQInfo info;
    cpVect p = {x, y};
    cpFilter f = {1, 0xffffffffu, 0xffffffffu}; /* mkv_env.robot.ROBOT_FILTER */
    return cp_pq(s->space, p, radius, f, &info) == NULL;
}

/* SensorSuite.draw_block in C: the next block of noise rows, bias + std * standard normal, drawn
 * row by row, channel by channel from the slot's bit generator (numpy fills its (rows, channels)
 * array in that order), as two roundings like numpy's ``block *= std; block += bias``. */
static void refill_noise(Slot *s)
{
    bitgen_t *g = s->gen;
    for (int r = 0; r < NOISE_ROWS; r++)
        for (int c = 0; c < NCH; c++) {
            double z = random_standard_normal(g);
            double t = z * s->nstd[c];
            s->noise[NCH * r + c] = t + s->nbias[c];
        }
    s->row = 0;
}

/* 1 when the slot has used its noise block and cannot draw the next itself (Python must). */
static inline int needs_noise(const Slot *s)
{
    return s->row >= NOISE_ROWS && s->gen == NULL;
}

/* SensorSuite.read on slot i's current state: the observation into row i of the obs buffer.
 * Returns 0 or an error code. */
static int read_sensors(BatchObject *b, Py_ssize_t i)
{
    Slot *s = &b->slots[i];
    if (s->row >= NOISE_ROWS) /* (only reached with a bit generator bound: see needs_noise) */
        refill_noise(s);
    const double *P = b->P;
    double *v = s->v;
    const int64_t *c = s->contacts;
    double tick = P[P_TICK];
    double dt_ = floor(v[S_DRIVE_ANGLE] / tick), rt_ = floor(v[S_ROLLER_ANGLE] / tick);
    double d0 = v[V_TICK_D], r0 = v[V_TICK_R];
    v[V_TICK_D] = dt_;
    v[V_TICK_R] = rt_;
    double i_d = v[S_I_DRIVE], i_s = v[S_I_STEER];
    const double *nz = s->noise + NCH * s->row;
    s->row += 1;
    double angle = cp_get_a(s->body);
    double truth[NCH];
    truth[0] = (dt_ - d0) + nz[0];
    truth[1] = (rt_ - r0) + nz[1];
    truth[2] = v[S_DELTA] + nz[2];
    truth[3] = py_mod(angle + nz[3] + M_PI, 2.0 * M_PI) - M_PI;
    truth[4] = (double)(c[2] > 0) + nz[4];
    truth[5] = (double)(c[3] > 0) + nz[5];
    truth[6] = (double)(c[4] > 0) + nz[6];
    truth[7] = i_d + nz[7];
    truth[8] = i_s + nz[8];
    truth[9] = P[P_BATT_V] - P[P_BATT_R] * (fabs(i_d) + fabs(i_s)) + nz[9];
    float *obs = OUT(b, O_OBS, float) + NCH * i;
    for (int k = 0; k < NCH; k++) {
        double y = truth[k] * b->iq[k];
        if (!isfinite(y))
            return s->err = ERR_NONFINITE;
        double r = rint(y);
        if (r == 0.0)
            r = 0.0;
        double val = r * b->q[k];
        double m = (b->lo[k] > val) ? b->lo[k] : val;
        obs[k] = (float)((b->hi[k] < m) ? b->hi[k] : m);
    }
    return 0;
}

/* Returns the slot's error code (0 = fine). Results go to the output buffers at row i. */
static int step_slot(BatchObject *b, Py_ssize_t i, long drive, long steer)
{
    Slot *s = &b->slots[i];
    const double *P = b->P;
    double *v = s->v;
    if (s->body == NULL)
        return s->err = ERR_UNBOUND;
    /* World.step: the floor under the drive wheel, looked up once per period */
    if (s->npatch)
        v[V_MU] = floor_scale(b->K[K_XD], s->body, s->patches, s->npatch);
    advance_one(b->K, s->body, s->space, drive, steer, P[P_DT], (long)P[P_SUBSTEPS], v[V_MU], v,
                1);

    /* SensorSuite.read */
    const int64_t *c = s->contacts;
    if (read_sensors(b, i))
        return s->err;
    double angle = cp_get_a(s->body);

    /* MKVEnv._pose + MotionTracker.update */
    cpVect pos = cp_get_p(s->body);
    double x = pos.x, y = pos.y, heading = remainder(angle, 2.0 * M_PI);
    double dx = x - v[V_X], dy = y - v[V_Y];
    double step = py_hypot(dx, dy);
    double mid = v[V_HEAD] + 0.5 * remainder(heading - v[V_HEAD], 2.0 * M_PI);
    double progress = dx * cos(mid) + dy * sin(mid);
    v[V_X] = x;
    v[V_Y] = y;
    v[V_HEAD] = heading;
    v[V_DIST] += step;
    v[V_LAST] = step;
    int stuck = drive != 0 && step < P[P_STUCK_SPEED] * P[P_PERIOD];
    v[V_STUCK_RUN] = stuck ? v[V_STUCK_RUN] + 1.0 : 0.0;
    double events = (double)c[0];
    int collision = events > v[V_EVENTS];
    if (collision)
        v[V_COLLS] += 1.0;
    v[V_EVENTS] = events;
    v[V_FWD] = progress > 1e-3 ? v[V_FWD] + progress : 0.0;
    int escaped = 0;
    if (v[V_IN_JAM] != 0.0) {
        if (!stuck && v[V_FWD] >= P[P_ESC_FWD] &&
            py_hypot(x - v[V_JAM_X], y - v[V_JAM_Y]) >= P[P_ESC_DIST] &&
            is_clear(s, x, y, P[P_FREE_CLEAR])) {
            v[V_IN_JAM] = 0.0;
            v[V_ESCAPES] += 1.0;
            escaped = 1;
        }
    } else if (v[V_STUCK_RUN] >= P[P_JAM_STEPS]) {
        v[V_IN_JAM] = 1.0;
        v[V_JAMS] += 1.0;
        v[V_JAM_X] = x;
        v[V_JAM_Y] = y;
    }

    /* the env class's _reward and _terminated */
    double reward;
    int terminated = 0;
    int kind = (int)P[P_KIND];
    if (kind == KIND_WANDER || kind == KIND_JAM) {
        reward = P[P_PROGRESS] * progress - P[P_STUCK_PEN] * (double)stuck -
                 P[P_COLL_PEN] * (double)collision;
        if (kind == KIND_JAM) {
            reward = reward + P[P_ESC_REWARD] * (double)escaped;
            terminated = escaped;
        }
    } else if (kind == KIND_WANDER_V1) {
        double new_cell = 0.0;
        if (progress > 0) {
            int r = cell_add(s, floor(x / P[P_CELL]), floor(y / P[P_CELL]));
            if (r < 0)
                return s->err = ERR_CELL;
            new_cell = (double)r;
        }
        int still = v[V_LAST] < P[P_STUCK_SPEED] * P[P_PERIOD];
        reward = P[P_COVERAGE] * new_cell - P[P_STILL_PEN] * (double)still -
                 P[P_STUCK_PEN] * (double)stuck - P[P_JAM_PEN] * v[V_IN_JAM] -
                 P[P_COLL_PEN] * (double)collision;
    } else {
        double d = py_hypot(v[V_X] - v[V_JAM_X], v[V_Y] - v[V_JAM_Y]);
        double q = d / P[P_ESC_DIST];
        double phi = (1.0 < q) ? 1.0 : q;
        double shaped = P[P_SHAPING] * (phi - v[V_PHI]);
        v[V_PHI] = phi;
        reward = P[P_ESC_REWARD] * (double)escaped - P[P_TIME_PEN] -
                 P[P_STUCK_PEN] * (double)stuck - P[P_COLL_PEN] * (double)collision + shaped;
        terminated = escaped;
    }

    OUT(b, O_REW, double)[i] = reward;
    OUT(b, O_TERM, uint8_t)[i] = (uint8_t)terminated;
    OUT(b, O_STUCK, uint8_t)[i] = (uint8_t)stuck;
    OUT(b, O_BUMPED, uint8_t)[i] = (uint8_t)(c[2] > 0 || c[3] > 0 || c[4] > 0);
    OUT(b, O_COLL, uint8_t)[i] = (uint8_t)collision;
    OUT(b, O_DIST, double)[i] = v[V_DIST];
    OUT(b, O_JAMS, int64_t)[i] = (int64_t)v[V_JAMS];
    OUT(b, O_ESC, int64_t)[i] = (int64_t)v[V_ESCAPES];
    OUT(b, O_COLLS, int64_t)[i] = (int64_t)v[V_COLLS];
    OUT(b, O_IN_JAM, uint8_t)[i] = (uint8_t)(v[V_IN_JAM] != 0.0);
    double *pose = OUT(b, O_POSE, double) + 3 * i;
    pose[0] = x;
    pose[1] = y;
    pose[2] = heading;
    OUT(b, O_CELLS, int64_t)[i] = s->ncells;
    OUT(b, O_ESCAPED, uint8_t)[i] = (uint8_t)(v[V_ESCAPES] > 0.0);
    return 0;
}
