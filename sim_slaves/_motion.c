/* sim_slaves._motion: the plain-CSP cascade of a run of drives, every substep of a step in one call.
 *
 * Optional speed-up for sim_slaves.drive_bank.DriveBank._csp_motion; without it
 * the bank runs the same substeps as numpy operations on the run's arrays (the
 * reference). csp(...) takes the bank's arrays whole (float64, C-contiguous;
 * the limit mask bool) and the run a..b-1, and does, drive by drive, what the
 * numpy path does array by array, with the same operations in the same order
 * (each product and sum rounded on its own: no fused multiply-add; numpy's
 * NaN-propagating maximum / minimum / clip): the velocity and torque
 * feed-forward, then `steps` substeps of encoder, position P, speed limit,
 * velocity PI, torque limit and rotor. The drives do not interact, so the
 * results are the numpy path's bits (tests/unit/test_drive_bank_kernel.py
 * runs both side by side).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
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

typedef struct {
    Py_buffer view[KI_H + 1];
    int held[KI_H + 1];
} Buffers;

static void release(Buffers *bufs) {
    for (int i = 0; i <= KI_H; i++)
        if (bufs->held[i]) PyBuffer_Release(&bufs->view[i]);
}

/* argument i as a C-contiguous buffer of at least `count` items of format `fmt` ("d" or "?") */
static int take(Buffers *bufs, PyObject *const *args, int i, Py_ssize_t count, const char *fmt, int writable) {
    Py_buffer *v = &bufs->view[i];
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(args[i], v, flags) < 0) return -1;
    bufs->held[i] = 1;
    Py_ssize_t size = fmt[0] == 'd' ? (Py_ssize_t)sizeof(double) : 1;
    if (v->itemsize != size || v->format == NULL || strcmp(v->format, fmt) != 0 || v->len < count * size) {
        PyErr_Format(PyExc_ValueError, "csp: argument %d is not %zd items of format '%s'", i, count, fmt);
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
    if (take(bufs, args, i, count, "d", 0) < 0) return -1;
    *p = (const double *)bufs->view[i].buf;
    *stride = 1;
    return 0;
}

static PyObject *csp(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
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
        if (take(&bufs, args, i, b, i == LIMIT ? "?" : "d", i <= LIMIT) < 0) goto done;
    if (take(&bufs, args, TARGET, n, "d", 0) < 0) goto done;
    if (args[NOISE] != Py_None && take(&bufs, args, NOISE, n, "d", 0) < 0) goto done;
    for (int j = 0; j < 5; j++)
        if (factor(&bufs, args, CE + j, n, &c[j], &cs[j], &scalars[j]) < 0) goto done;

#define BANK(i) ((double *)bufs.view[i].buf + a)
    double *pos = BANK(POS), *vel = BANK(VEL), *integ = BANK(INTEG), *prev_target = BANK(PREV_TARGET);
    double *prev_vff = BANK(PREV_VFF), *tau_out = BANK(TAU), *tau_eff = BANK(TAU_EFF), *shaft = BANK(SHAFT);
    char *limit = (char *)bufs.view[LIMIT].buf + a;
    const double *vff_gain = BANK(VFF_GAIN), *tff_gain = BANK(TFF_GAIN), *kv = BANK(KV), *kp = BANK(KP);
    const double *tmax = BANK(TMAX), *load = BANK(LOAD), *epr = BANK(EPR), *rpe = BANK(RPE), *vmax = BANK(VMAX);
#undef BANK
    const double *target = (const double *)bufs.view[TARGET].buf;
    const double *noise = bufs.held[NOISE] ? (const double *)bufs.view[NOISE].buf : NULL;
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
        vel[i] = v;
        integ[i] = in;
        prev_target[i] = tgt;
        tau_out[i] = tau_eff[i] = shaft[i] = tau;
        limit[i] = hit;
        limited |= hit;
    }
    result = PyBool_FromLong(limited);
done:
    release(&bufs);
    return result;
}

static PyMethodDef motion_methods[] = {
    {"csp", (PyCFunction)(void (*)(void))csp, METH_FASTCALL,
     "csp(pos, vel, integ, prev_target, prev_vff, tau, tau_eff, shaft, limit, vff_gain, tff_gain, kv, kp, tmax, "
     "load, epr, rpe, vmax, target, noise, e, f, g, hh, ki_h, a, b, dt, steps, speed_limited) -> limited"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef motion_module = {
    PyModuleDef_HEAD_INIT, "sim_slaves._motion", "C speed-up for the drive bank's plain-CSP substeps", -1,
    motion_methods,
};

PyMODINIT_FUNC PyInit__motion(void) { return PyModule_Create(&motion_module); }
