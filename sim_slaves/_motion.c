/* sim_slaves._motion: a step of the drive bank's plain-CSP path for a run of drives in two calls.
 *
 * Optional speed-up for sim_slaves.drive_bank.DriveBank._csp_motion and
 * _csp_outputs; without it the bank does the same as numpy operations on the
 * run's arrays (the reference). Both functions take the bank's arrays whole
 * (C-contiguous float64 / int64 / bool) and the run a..b-1, and do, drive by
 * drive, what the numpy path does array by array, with the same operations in
 * the same order (each product and sum rounded on its own: no fused
 * multiply-add; numpy's NaN-propagating maximum / minimum / clip). The drives
 * do not interact, so the results are the numpy path's bits
 * (tests/unit/test_drive_bank_kernel.py runs both side by side).
 *
 * csp(...): the velocity and torque feed-forward, then `steps` substeps of
 * encoder, position P, speed limit, velocity PI, torque limit and rotor.
 * csp_outputs(...): statusword, following error, actual values; it declines
 * (returns False, leaves fe_time alone) when a drive's following error is
 * beyond its window or a value does not fit int64 (NaN): numpy then does it.
 * Bank(...): the kernel's hold on one bank's arrays, taken once, and two calls per cycle on it:
 * csp_cycle (the target from the raw targets, csp, csp_outputs: the plain CSP path's cycle in one call) and
 * idle_cycle (DriveBank._idle's rotors coasting, no drive powered, through `steps` substeps, then its
 * outputs; it declines the outputs, returns False with the motion done, when a value does not fit int64 or
 * a state has no statusword bits in the table: numpy then does them). Ideal encoders only.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <float.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

/* every product and sum rounds on its own, as in numpy: no fused multiply-add */
#if defined(__clang__)
#pragma STDC FP_CONTRACT OFF
#elif defined(__GNUC__)
#pragma GCC optimize("fp-contract=off")
#endif

/* numpy's maximum / minimum (and clip's bounds) on doubles: a NaN operand is the result; of equal
 * operands (+0 and -0) the second */
static inline double np_max(double x, double y) { return isnan(x) ? x : (x > y ? x : y); }
static inline double np_min(double x, double y) { return isnan(x) ? x : (x < y ? x : y); }

/* the arguments, in order */
enum {
    /* bank arrays written: float64 ... */
    POS, VEL, INTEG, PREV_TARGET, PREV_VFF, TAU, TAU_EFF, SHAFT,
    LIMIT, /* ... and bool */
    /* bank arrays read: float64 */
    VFF_GAIN, TFF_GAIN, KV, KP, TMAX, LOAD, EPR, RPE, VMAX,
    /* the run's: target [rad] (float64), encoder noise [counts] (float64 or None) */
    TARGET, NOISE,
    /* the exact-integration factors of a substep and ki h: a float, or float64 of the run */
    CE, CF, CG, CHH, KI_H,
    /* a, b, dt [s], steps, speed limited */
    A, B, DT, STEPS, SPEED_LIMITED,
    NARGS
};
#define N_BANK (VMAX + 1)

#define MAX_BUFFERS 32

typedef struct {
    Py_buffer view[MAX_BUFFERS];
    int held[MAX_BUFFERS];
} Buffers;

static void release(Buffers *bufs) {
    for (int i = 0; i < MAX_BUFFERS; i++)
        if (bufs->held[i]) PyBuffer_Release(&bufs->view[i]);
}

/* argument i as a C-contiguous buffer of at least `count` items of kind `kind`: 'd' float64, 'q' int64,
 * '?' bool */
static int take(Buffers *bufs, PyObject *const *args, int i, Py_ssize_t count, char kind, int writable) {
    Py_buffer *v = &bufs->view[i];
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(args[i], v, flags) < 0) return -1;
    bufs->held[i] = 1;
    const char *f = v->format ? v->format : "B";
    Py_ssize_t size = kind == '?' ? 1 : 8;
    int ok = kind == 'd'   ? strcmp(f, "d") == 0
             : kind == '?' ? strcmp(f, "?") == 0
                           : (strcmp(f, "q") == 0 || (strcmp(f, "l") == 0 && sizeof(long) == 8));
    if (!ok || v->itemsize != size || v->len < count * size) {
        PyErr_Format(PyExc_ValueError, "argument %d is not %zd items of kind '%c'", i, count, kind);
        return -1;
    }
    return 0;
}

/* a factor: one float for every drive (stride 0), or one per drive of the run */
static int factor(Buffers *bufs, PyObject *const *args, int i, Py_ssize_t count, const double **p,
                  Py_ssize_t *stride, double *scalar) {
    if (PyFloat_Check(args[i])) {
        *scalar = PyFloat_AS_DOUBLE(args[i]);
        *p = scalar;
        *stride = 0;
        return 0;
    }
    if (take(bufs, args, i, count, 'd', 0) < 0) return -1;
    *p = (const double *)bufs->view[i].buf;
    *stride = 1;
    return 0;
}

static int csp_run(const Py_buffer *view, const double *target, const double *noise, const double *const *c,
                   const Py_ssize_t *cs, Py_ssize_t a, Py_ssize_t b, double dt, long steps, int speed_limited);

static PyObject *csp(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (nargs != NARGS) {
        PyErr_Format(PyExc_TypeError, "csp: %d arguments, got %zd", NARGS, nargs);
        return NULL;
    }
    Py_ssize_t a = PyLong_AsSsize_t(args[A]), b = PyLong_AsSsize_t(args[B]);
    double dt = PyFloat_AsDouble(args[DT]);
    long steps = PyLong_AsLong(args[STEPS]);
    int speed_limited = PyObject_IsTrue(args[SPEED_LIMITED]);
    if (PyErr_Occurred() || speed_limited < 0) return NULL;
    if (a < 0 || b < a || steps < 1) {
        PyErr_Format(PyExc_ValueError, "csp: need 0 <= a <= b and steps >= 1, got a=%zd b=%zd steps=%ld", a, b,
                     steps);
        return NULL;
    }
    Py_ssize_t n = b - a;
    Buffers bufs;
    memset(bufs.held, 0, sizeof(bufs.held));
    PyObject *result = NULL;
    const double *c[5];
    Py_ssize_t cs[5];
    double scalars[5];
    for (int i = 0; i < N_BANK; i++)
        if (take(&bufs, args, i, b, i == LIMIT ? '?' : 'd', i <= LIMIT) < 0) goto done;
    if (take(&bufs, args, TARGET, n, 'd', 0) < 0) goto done;
    if (args[NOISE] != Py_None && take(&bufs, args, NOISE, n, 'd', 0) < 0) goto done;
    for (int j = 0; j < 5; j++)
        if (factor(&bufs, args, CE + j, n, &c[j], &cs[j], &scalars[j]) < 0) goto done;
    result = PyBool_FromLong(csp_run(bufs.view, (const double *)bufs.view[TARGET].buf,
                                     bufs.held[NOISE] ? (const double *)bufs.view[NOISE].buf : NULL, c, cs, a, b, dt,
                                     steps, speed_limited));
done:
    release(&bufs);
    return result;
}

/* csp's substeps of drives a..b-1 on the bank arrays `view` (indexed as csp's arguments, checked); target and
 * noise of the run (noise NULL: none), the factors with their strides (0: one for all); returns limited */
static int csp_run(const Py_buffer *view, const double *target, const double *noise, const double *const *c,
                   const Py_ssize_t *cs, Py_ssize_t a, Py_ssize_t b, double dt, long steps, int speed_limited) {
    Py_ssize_t n = b - a;
#define BANK(i) ((double *)view[i].buf + a)
    double *pos = BANK(POS), *vel = BANK(VEL), *integ = BANK(INTEG), *prev_target = BANK(PREV_TARGET);
    double *prev_vff = BANK(PREV_VFF), *tau_out = BANK(TAU), *tau_eff = BANK(TAU_EFF), *shaft = BANK(SHAFT);
    char *limit = (char *)view[LIMIT].buf + a;
    const double *vff_gain = BANK(VFF_GAIN), *tff_gain = BANK(TFF_GAIN), *kv = BANK(KV), *kp = BANK(KP);
    const double *tmax = BANK(TMAX), *load = BANK(LOAD), *epr = BANK(EPR), *rpe = BANK(RPE), *vmax = BANK(VMAX);
#undef BANK
    int limited = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        double e = c[0][i * cs[0]], f = c[1][i * cs[1]], g = c[2][i * cs[2]], hh = c[3][i * cs[3]];
        double ki_h = c[4][i * cs[4]];
        double prev_t = prev_target[i], tgt = target[i];
        double vff = (tgt - prev_t) / dt;
        double aff = (vff - prev_vff[i]) / dt;
        prev_vff[i] = vff;
        vff *= vff_gain[i];
        aff *= tff_gain[i];
        double step = tgt - prev_t;
        double p = pos[i], v = vel[i], in = integ[i], tau = v;
        double hi = tmax[i], lo = -tmax[i], vhi = vmax[i], vlo = -vmax[i];
        double e_pr = epr[i], r_pe = rpe[i], k_p = kp[i], k_v = kv[i], ld = load[i];
        char hit = 0;
        for (long k = 1; k <= steps; k++) {
            double measured = floor(p * e_pr + 0.5);
            if (noise) measured += noise[i];
            measured *= r_pe;
            double ev = prev_t + step * ((double)k / (double)steps);
            ev -= measured;
            ev *= k_p;
            ev += vff;
            if (speed_limited) ev = np_min(np_max(ev, vlo), vhi); /* np.clip */
            ev -= v;                                              /* velocity error */
            in = np_min(np_max(in + ki_h * ev, lo), hi);
            tau = k_v * ev;
            tau += in;
            tau += aff;
            double clipped = np_min(np_max(tau, lo), hi);
            if (clipped != tau) hit = 1;
            tau = clipped;
            double net = tau - ld;
            double p_new = p + v * g + net * hh;
            v = v * e + net * f;
            p = p_new;
        }
        pos[i] = p;
        vel[i] = fabs(v) < DBL_MIN ? 0.0 : v; /* a subnormal: 0 (drive_bank._flush_subnormal) */
        integ[i] = fabs(in) < DBL_MIN ? 0.0 : in;
        prev_target[i] = tgt;
        tau_out[i] = tau_eff[i] = shaft[i] = tau;
        limit[i] = hit;
        limited |= hit;
    }
    return limited;
}

/* the arguments of csp_outputs, in order */
enum {
    /* bank arrays written: int64 ..., and float64 */
    O_STATUSWORD, O_FOLLOWING_ERROR, O_POSITION_COUNTS, O_VELOCITY_COUNTS, O_TORQUE_PERMILLE, O_FE_TIME,
    /* bank arrays read: float64 ... */
    O_POS, O_VEL, O_TAU, O_CPR, O_EPR, O_ENC_TO_COUNTS, O_VPR, O_RATED,
    /* ... int64 ... */
    O_NOISE, O_FE_WINDOW, O_POSITION_WINDOW,
    /* ... and bool */
    O_LIMIT,
    /* the run's target [rad] (float64) */
    O_TARGET,
    /* a, b, ideal encoder, limited; statusword: following, following and target reached, limit bit */
    O_A, O_B, O_IDEAL, O_LIMITED, O_SW_CSP, O_SW_REACHED, O_SW_LIMIT,
    O_NARGS
};

/* a float that is a whole number, as int64 the way numpy casts it; 0 where it does not fit (NaN, too big) */
static inline int fits(double x) { return x >= -9223372036854775808.0 && x < 9223372036854775808.0; }

static int csp_outputs_run(const Py_buffer *view, const double *target, Py_ssize_t a, Py_ssize_t b, int ideal,
                           int limited, long long sw_csp, long long sw_reached, long long sw_limit);

static PyObject *csp_outputs(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (nargs != O_NARGS) {
        PyErr_Format(PyExc_TypeError, "csp_outputs: %d arguments, got %zd", O_NARGS, nargs);
        return NULL;
    }
    Py_ssize_t a = PyLong_AsSsize_t(args[O_A]), b = PyLong_AsSsize_t(args[O_B]);
    int ideal = PyObject_IsTrue(args[O_IDEAL]), limited = PyObject_IsTrue(args[O_LIMITED]);
    long long sw_csp = PyLong_AsLongLong(args[O_SW_CSP]), sw_reached = PyLong_AsLongLong(args[O_SW_REACHED]);
    long long sw_limit = PyLong_AsLongLong(args[O_SW_LIMIT]);
    if (PyErr_Occurred() || ideal < 0 || limited < 0) return NULL;
    if (a < 0 || b < a) {
        PyErr_Format(PyExc_ValueError, "csp_outputs: need 0 <= a <= b, got a=%zd b=%zd", a, b);
        return NULL;
    }
    Py_ssize_t n = b - a;
    Buffers bufs;
    memset(bufs.held, 0, sizeof(bufs.held));
    PyObject *result = NULL;
    for (int i = 0; i <= O_LIMIT; i++) {
        char kind = i == O_LIMIT ? '?' : (i < O_FE_TIME || (i >= O_NOISE && i < O_LIMIT)) ? 'q' : 'd';
        if (take(&bufs, args, i, b, kind, i <= O_FE_TIME) < 0) goto done;
    }
    if (take(&bufs, args, O_TARGET, n, 'd', 0) < 0) goto done;
    result = PyBool_FromLong(csp_outputs_run(bufs.view, (const double *)bufs.view[O_TARGET].buf, a, b, ideal, limited,
                                             sw_csp, sw_reached, sw_limit));
done:
    release(&bufs);
    return result;
}

/* csp_outputs of drives a..b-1 on the bank arrays `view` (indexed as csp_outputs' arguments, checked) and the
 * run's target; returns whether it did them (0: numpy's turn, fe_time untouched) */
static int csp_outputs_run(const Py_buffer *view, const double *target, Py_ssize_t a, Py_ssize_t b, int ideal,
                           int limited, long long sw_csp, long long sw_reached, long long sw_limit) {
    Py_ssize_t n = b - a;
#define F(i) ((double *)view[i].buf + a)
#define Q(i) ((int64_t *)view[i].buf + a)
    int64_t *statusword = Q(O_STATUSWORD), *following_error = Q(O_FOLLOWING_ERROR);
    int64_t *position_counts = Q(O_POSITION_COUNTS), *velocity_counts = Q(O_VELOCITY_COUNTS);
    int64_t *torque_permille = Q(O_TORQUE_PERMILLE);
    double *fe_time = F(O_FE_TIME);
    const double *pos = F(O_POS), *vel = F(O_VEL), *tau = F(O_TAU), *cpr = F(O_CPR), *epr = F(O_EPR);
    const double *enc_to_counts = F(O_ENC_TO_COUNTS), *vpr = F(O_VPR), *rated = F(O_RATED);
    const int64_t *noise = Q(O_NOISE), *fe_window = Q(O_FE_WINDOW), *position_window = Q(O_POSITION_WINDOW);
#undef F
#undef Q
    const char *limit = (const char *)view[O_LIMIT].buf + a;
    int done_all = 1;
    for (Py_ssize_t i = 0; i < n; i++) {
        double pos_counts;
        if (!ideal) {
            double enc = floor(pos[i] * epr[i] + 0.5) + (double)noise[i];
            pos_counts = floor(enc * enc_to_counts[i] + 0.5);
        } else {
            pos_counts = floor(pos[i] * cpr[i] + 0.5);
        }
        double fe = floor(target[i] * cpr[i] + 0.5) - pos_counts;
        double afe = fabs(fe);
        double v = floor(vel[i] * vpr[i] + 0.5);
        double t = floor(tau[i] * 1000.0 / rated[i] + 0.5);
        if (afe > (double)fe_window[i] || !fits(fe) || !fits(pos_counts) || !fits(v) || !fits(t)) {
            done_all = 0; /* numpy does the run: the following-error timer, the fault, NaN */
            break;
        }
        long long sw = afe <= (double)position_window[i] ? sw_reached : sw_csp;
        if (limited && limit[i]) sw |= sw_limit;
        statusword[i] = (int64_t)sw;
        following_error[i] = (int64_t)fe;
        position_counts[i] = (int64_t)pos_counts;
        velocity_counts[i] = (int64_t)v;
        torque_permille[i] = (int64_t)t;
    }
    if (done_all)
        for (Py_ssize_t i = 0; i < n; i++) fe_time[i] = 0.0;
    return done_all;
}


/* the bank arrays of idle_run (Bank's idle_arrays), in order */
enum {
    /* bank arrays written: float64 ... */
    I_POS, I_VEL, I_PREV_TARGET, I_TAU, I_TAU_EFF, I_SHAFT,
    /* ... int64 ... */
    I_STATUSWORD, I_FOLLOWING_ERROR, I_POSITION_COUNTS, I_VELOCITY_COUNTS, I_TORQUE_PERMILLE,
    /* ... and bool */
    I_LIMIT,
    /* bank arrays read: int64 state, float64 load, cpr, vpr */
    I_STATE, I_LOAD, I_CPR, I_VPR,
    /* the statusword's state bits by state (int64, any length) */
    I_SW_BY_STATE,
    I_NARRAYS
};

/* idle's rotors and outputs of drives a..b-1 on the bank arrays `view` (indexed as its arguments, checked),
 * the factors with their strides; returns whether it did the outputs */
static int idle_run(const Py_buffer *view, const double *const *c, const Py_ssize_t *cs, Py_ssize_t a, Py_ssize_t b,
                    long steps, long long sw_remote, long long sw_voltage, long long nr) {
    Py_ssize_t n = b - a;
#define F(i) ((double *)view[i].buf + a)
#define Q(i) ((int64_t *)view[i].buf + a)
    double *pos = F(I_POS), *vel = F(I_VEL), *prev_target = F(I_PREV_TARGET);
    double *tau = F(I_TAU), *tau_eff = F(I_TAU_EFF), *shaft = F(I_SHAFT);
    int64_t *statusword = Q(I_STATUSWORD), *following_error = Q(I_FOLLOWING_ERROR);
    int64_t *position_counts = Q(I_POSITION_COUNTS), *velocity_counts = Q(I_VELOCITY_COUNTS);
    int64_t *torque_permille = Q(I_TORQUE_PERMILLE);
    const int64_t *state = Q(I_STATE);
    const double *load = F(I_LOAD), *cpr = F(I_CPR), *vpr = F(I_VPR);
#undef F
#undef Q
    char *limit = (char *)view[I_LIMIT].buf + a;
    const int64_t *sw_by_state = (const int64_t *)view[I_SW_BY_STATE].buf;
    Py_ssize_t n_states = view[I_SW_BY_STATE].len / 8;
    int outputs = 1;
    for (Py_ssize_t i = 0; i < n; i++) {
        double e = c[0][i * cs[0]], f = c[1][i * cs[1]], g = c[2][i * cs[2]], hh = c[3][i * cs[3]];
        double p = pos[i], v = vel[i], net = -load[i];
        for (long k = 0; k < steps; k++) {
            double p_new = p + v * g + net * hh;
            v = v * e + net * f;
            p = p_new;
        }
        v = fabs(v) < DBL_MIN ? 0.0 : v; /* a subnormal: 0 (drive_bank._flush_subnormal) */
        pos[i] = p;
        vel[i] = v;
        prev_target[i] = p;
        tau[i] = tau_eff[i] = shaft[i] = 0.0;
        limit[i] = 0;
        double counts = floor(p * cpr[i] + 0.5), speed = floor(v * vpr[i] + 0.5);
        if (!fits(counts) || !fits(speed) || state[i] < 0 || state[i] >= n_states) outputs = 0;
    }
    if (outputs)
        for (Py_ssize_t i = 0; i < n; i++) {
            long long s = state[i];
            statusword[i] = sw_by_state[s] | (s != nr ? sw_remote | sw_voltage : sw_remote);
            following_error[i] = 0;
            position_counts[i] = (int64_t)floor(pos[i] * cpr[i] + 0.5);
            velocity_counts[i] = (int64_t)floor(vel[i] * vpr[i] + 0.5);
            torque_permille[i] = 0;
        }
    return outputs;
}

/* Bank(csp_arrays, out_arrays, target_position, rpc, target): the kernel's hold on one drive bank's arrays,
 * taken once (the buffers of csp's bank arguments, of csp_outputs' bank arguments, in their orders; the raw
 * target positions (int64), radians per count and a scratch row for the target [rad] (float64)), so a cycle
 * of the plain CSP path is one call: Bank.csp_cycle. */
typedef struct {
    PyObject_HEAD
    Buffers csp_bufs, out_bufs, idle_bufs, extra; /* extra: 0 target_position, 1 rpc, 2 target */
    Py_ssize_t n;
} BankObject;

static void bank_dealloc(BankObject *self) {
    release(&self->csp_bufs);
    release(&self->out_bufs);
    release(&self->idle_bufs);
    release(&self->extra);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int bank_init(BankObject *self, PyObject *args, PyObject *kwds) {
    PyObject *csp_arrays, *out_arrays, *idle_arrays, *rest[3];
    static char *names[] = {"csp_arrays", "out_arrays", "idle_arrays", "target_position", "rpc", "target", NULL};
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "O!O!O!OOO", names, &PyTuple_Type, &csp_arrays, &PyTuple_Type,
                                     &out_arrays, &PyTuple_Type, &idle_arrays, &rest[0], &rest[1], &rest[2]))
        return -1;
    Buffers *all[] = {&self->csp_bufs, &self->out_bufs, &self->idle_bufs, &self->extra};
    for (int k = 0; k < 4; k++) {
        release(all[k]);
        memset(all[k]->held, 0, sizeof(all[k]->held));
    }
    if (PyTuple_GET_SIZE(csp_arrays) != N_BANK || PyTuple_GET_SIZE(out_arrays) != O_LIMIT + 1 ||
        PyTuple_GET_SIZE(idle_arrays) != I_NARRAYS) {
        PyErr_Format(PyExc_ValueError, "Bank: %d csp, %d csp_outputs and %d idle arrays", N_BANK, O_LIMIT + 1,
                     I_NARRAYS);
        return -1;
    }
    if (take(&self->extra, rest, 1, 0, 'd', 0) < 0) return -1;
    Py_ssize_t n = self->n = self->extra.view[1].len / 8;
    if (take(&self->extra, rest, 0, n, 'q', 0) < 0 || take(&self->extra, rest, 2, n, 'd', 1) < 0) return -1;
    PyObject *const *items = &PyTuple_GET_ITEM(csp_arrays, 0);
    for (int i = 0; i < N_BANK; i++)
        if (take(&self->csp_bufs, items, i, n, i == LIMIT ? '?' : 'd', i <= LIMIT) < 0) return -1;
    items = &PyTuple_GET_ITEM(out_arrays, 0);
    for (int i = 0; i <= O_LIMIT; i++) {
        char kind = i == O_LIMIT ? '?' : (i < O_FE_TIME || (i >= O_NOISE && i < O_LIMIT)) ? 'q' : 'd';
        if (take(&self->out_bufs, items, i, n, kind, i <= O_FE_TIME) < 0) return -1;
    }
    items = &PyTuple_GET_ITEM(idle_arrays, 0);
    for (int i = 0; i <= I_VPR; i++) {
        char kind = i == I_LIMIT ? '?' : (i >= I_STATUSWORD && i < I_LIMIT) || i == I_STATE ? 'q' : 'd';
        if (take(&self->idle_bufs, items, i, n, kind, i <= I_LIMIT) < 0) return -1;
    }
    if (take(&self->idle_bufs, items, I_SW_BY_STATE, 0, 'q', 0) < 0) return -1;
    return 0;
}

/* the arguments of Bank.csp_cycle, in order */
enum { C_A, C_B, C_DT, C_STEPS, C_CE, C_CF, C_CG, C_CHH, C_KI_H, C_SPEED_LIMITED, C_SW_CSP, C_SW_REACHED, C_SW_LIMIT,
       C_NARGS };

/* drives a..b-1 of the bank and at least one substep: 0, else -1 with a ValueError naming `name` */
static int bank_range(const char *name, const BankObject *self, Py_ssize_t a, Py_ssize_t b, long steps) {
    if (a < 0 || b < a || b > self->n || steps < 1) {
        PyErr_Format(PyExc_ValueError, "%s: need 0 <= a <= b <= %zd and steps >= 1, got a=%zd b=%zd steps=%ld", name,
                     self->n, a, b, steps);
        return -1;
    }
    return 0;
}

/* one cycle of the plain CSP path of drives a..b-1 (ideal encoders, no command delay, no position limits): the
 * target from the raw target positions, csp, csp_outputs; returns limited | outputs done << 1 */
static PyObject *bank_csp_cycle(BankObject *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != C_NARGS) {
        PyErr_Format(PyExc_TypeError, "csp_cycle: %d arguments, got %zd", C_NARGS, nargs);
        return NULL;
    }
    Py_ssize_t a = PyLong_AsSsize_t(args[C_A]), b = PyLong_AsSsize_t(args[C_B]);
    double dt = PyFloat_AsDouble(args[C_DT]);
    long steps = PyLong_AsLong(args[C_STEPS]);
    int speed_limited = PyObject_IsTrue(args[C_SPEED_LIMITED]);
    long long sw_csp = PyLong_AsLongLong(args[C_SW_CSP]), sw_reached = PyLong_AsLongLong(args[C_SW_REACHED]);
    long long sw_limit = PyLong_AsLongLong(args[C_SW_LIMIT]);
    if (PyErr_Occurred() || speed_limited < 0) return NULL;
    if (bank_range("csp_cycle", self, a, b, steps) < 0) return NULL;
    Buffers bufs;
    memset(bufs.held, 0, sizeof(bufs.held));
    PyObject *result = NULL;
    const double *c[5];
    Py_ssize_t cs[5];
    double scalars[5];
    for (int j = 0; j < 5; j++)
        if (factor(&bufs, args, C_CE + j, b - a, &c[j], &cs[j], &scalars[j]) < 0) goto done;
    const int64_t *tp = (const int64_t *)self->extra.view[0].buf;
    const double *rpc = (const double *)self->extra.view[1].buf;
    double *target = (double *)self->extra.view[2].buf + a;
    for (Py_ssize_t i = a; i < b; i++) target[i - a] = (double)tp[i] * rpc[i]; /* tp * rpc, as numpy */
    int limited = csp_run(self->csp_bufs.view, target, NULL, c, cs, a, b, dt, steps, speed_limited);
    int outputs = csp_outputs_run(self->out_bufs.view, target, a, b, 1, limited, sw_csp, sw_reached, sw_limit);
    result = PyLong_FromLong(limited | outputs << 1);
done:
    release(&bufs);
    return result;
}

/* the arguments of Bank.idle_cycle, in order */
enum { D_A, D_B, D_STEPS, D_CE, D_CF, D_CG, D_CHH, D_SW_REMOTE, D_SW_VOLTAGE, D_NR, D_NARGS };

/* DriveBank._idle of drives a..b-1 (ideal encoders): rotors coast through `steps` substeps, then the outputs;
 * returns whether it did the outputs (False: a value does not fit int64, numpy's turn; the motion done) */
static PyObject *bank_idle_cycle(BankObject *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != D_NARGS) {
        PyErr_Format(PyExc_TypeError, "idle_cycle: %d arguments, got %zd", D_NARGS, nargs);
        return NULL;
    }
    Py_ssize_t a = PyLong_AsSsize_t(args[D_A]), b = PyLong_AsSsize_t(args[D_B]);
    long steps = PyLong_AsLong(args[D_STEPS]);
    long long sw_remote = PyLong_AsLongLong(args[D_SW_REMOTE]), sw_voltage = PyLong_AsLongLong(args[D_SW_VOLTAGE]);
    long long nr = PyLong_AsLongLong(args[D_NR]);
    if (PyErr_Occurred()) return NULL;
    if (bank_range("idle_cycle", self, a, b, steps) < 0) return NULL;
    Buffers bufs;
    memset(bufs.held, 0, sizeof(bufs.held));
    PyObject *result = NULL;
    const double *c[4];
    Py_ssize_t cs[4];
    double scalars[4];
    for (int j = 0; j < 4; j++)
        if (factor(&bufs, args, D_CE + j, b - a, &c[j], &cs[j], &scalars[j]) < 0) goto done;
    result = PyBool_FromLong(idle_run(self->idle_bufs.view, c, cs, a, b, steps, sw_remote, sw_voltage, nr));
done:
    release(&bufs);
    return result;
}

static PyMethodDef bank_methods[] = {
    {"idle_cycle", (PyCFunction)(void (*)(void))bank_idle_cycle, METH_FASTCALL,
     "idle_cycle(a, b, steps, e, f, g, hh, sw_remote, sw_voltage, nr) -> outputs done (False: numpy's turn)"},
    {"csp_cycle", (PyCFunction)(void (*)(void))bank_csp_cycle, METH_FASTCALL,
     "csp_cycle(a, b, dt, steps, e, f, g, hh, ki_h, speed_limited, sw_csp, sw_reached, sw_limit) -> "
     "limited | outputs done << 1 (outputs not done: numpy's turn, the target in the scratch row)"},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject BankType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "sim_slaves._motion.Bank",
    .tp_basicsize = sizeof(BankObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Bank(csp_arrays, out_arrays, target_position, rpc, target): a drive bank's arrays held once",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)bank_init,
    .tp_dealloc = (destructor)bank_dealloc,
    .tp_methods = bank_methods,
};

static PyMethodDef motion_methods[] = {
    {"csp", (PyCFunction)(void (*)(void))csp, METH_FASTCALL,
     "csp(pos, vel, integ, prev_target, prev_vff, tau, tau_eff, shaft, limit, vff_gain, tff_gain, kv, kp, tmax, "
     "load, epr, rpe, vmax, target, noise, e, f, g, hh, ki_h, a, b, dt, steps, speed_limited) -> limited"},
    {"csp_outputs", (PyCFunction)(void (*)(void))csp_outputs, METH_FASTCALL,
     "csp_outputs(statusword, following_error, position_counts, velocity_counts, torque_permille, fe_time, pos, "
     "vel, tau, cpr, epr, enc_to_counts, vpr, rated, noise, fe_window, position_window, limit, target, a, b, "
     "ideal_encoder, limited, sw_csp, sw_reached, sw_limit) -> done (False: numpy's turn)"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef motion_module = {
    PyModuleDef_HEAD_INIT, "sim_slaves._motion", "C speed-up for the drive bank's plain-CSP substeps", -1,
    motion_methods,
};

PyMODINIT_FUNC PyInit__motion(void) {
    if (PyType_Ready(&BankType) < 0) return NULL;
    PyObject *m = PyModule_Create(&motion_module);
    if (m == NULL) return NULL;
    if (PyModule_AddObjectRef(m, "Bank", (PyObject *)&BankType) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
