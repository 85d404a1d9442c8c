/* sim_slaves._dcloop: the ESC time-control loop of a line of emulated clocks in one call.
 *
 * Optional speed-up for sim_slaves.ethercat.dc.DcLine.flush; without it the
 * line runs DcSlaveClock.time_control_input clock by clock. The state of the
 * line is one array of Clock records (ClockArrays.rec in dc_clock.py, a numpy
 * structured array with align=True; Python checks the layout against
 * `layout` before use). time_control(rec, received, now, a, b, ref_ns) gives
 * clocks a..b-1 the received system time `received` (compared on 32 bits) at
 * true times now[a..b-1] (int64 ns), with the operations of
 * DcSlaveClock.time_control_input in the same order: the same bits
 * (tests/unit/test_esc_dc.py runs a line against clocks alone, with and
 * without this module).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stddef.h>
#include <stdint.h>

/* every product and sum rounds on its own, as in Python: no fused multiply-add */
#if defined(__clang__)
#pragma STDC FP_CONTRACT OFF
#elif defined(__GNUC__)
#pragma GCC optimize("fp-contract=off")
#endif

typedef struct {
    uint64_t anchor_local; /* local ns at the anchor (64-bit, wraps) */
    double anchor_frac;    /* sub-ns part of it */
    int64_t anchor_true;   /* true ns of the anchor */
    double rate;           /* local ns per true ns */
    double drift_factor;   /* 1 + drift */
    uint64_t offset;       /* 0x0920 */
    uint64_t delay;        /* 0x0928 */
    uint64_t last_sample;  /* local ns of the last loop sample */
    double diff;           /* filtered system time difference (ns) */
    double integral;       /* integral rate correction (fraction) */
    double correction;     /* rate correction (fraction) */
    double weight;         /* 2^-depth of the difference filter */
    double tau;            /* loop time constant (ns) */
    double cmax;           /* bound of the correction (fraction) */
    uint8_t has_last;
    uint8_t primed;
} Clock;

static void step(Clock *c, uint64_t received, int64_t now, double ref_ns) {
    double exact = c->anchor_frac + (double)(now - c->anchor_true) * c->rate;
    double whole = floor(exact);
    uint64_t local = c->anchor_local + (uint64_t)(int64_t)whole;
    c->anchor_local = local;
    c->anchor_frac = exact - whole;
    c->anchor_true = now;
    uint64_t d = (local + c->offset - c->delay - received) & 0xFFFFFFFFu;
    double delta = (double)(d >= 0x80000000u ? (int64_t)d - ((int64_t)1 << 32) : (int64_t)d);
    double dt = c->has_last ? (double)(local - c->last_sample) : 0.0;
    c->last_sample = local;
    c->has_last = 1;
    double tau = c->tau, cmax = c->cmax;
    double alpha = c->weight * dt / ref_ns;
    if (alpha > 1.0) alpha = 1.0;
    double diff = c->primed ? c->diff + alpha * (delta - c->diff) : delta;
    double x = (dt < tau ? dt : tau) / tau;
    double prop = -2.0 * diff / tau;
    double integral = c->integral;
    if (c->primed && !(fabs(integral + prop) >= cmax)) integral = integral - diff * x / tau;
    if (integral > cmax) integral = cmax;
    else if (integral < -cmax) integral = -cmax;
    double corr = integral + prop;
    if (corr > cmax) corr = cmax;
    else if (corr < -cmax) corr = -cmax;
    c->diff = diff;
    c->integral = integral;
    c->correction = corr;
    c->primed = 1;
    c->rate = c->drift_factor * (1.0 + corr);
}

static PyObject *time_control(PyObject *self, PyObject *args) {
    Py_buffer rec, now;
    unsigned long long received;
    Py_ssize_t a, b;
    double ref_ns;
    if (!PyArg_ParseTuple(args, "w*Ky*nnd", &rec, &received, &now, &a, &b, &ref_ns)) return NULL;
    Py_ssize_t n = rec.len / (Py_ssize_t)sizeof(Clock);
    PyObject *result = NULL;
    if (rec.len % (Py_ssize_t)sizeof(Clock) || now.len < n * (Py_ssize_t)sizeof(int64_t) || a < 0 || b > n) {
        PyErr_SetString(PyExc_ValueError, "time_control: records, times or range do not fit");
    } else {
        Clock *clocks = (Clock *)rec.buf;
        const int64_t *t = (const int64_t *)now.buf;
        for (Py_ssize_t i = a; i < b; i++) step(&clocks[i], (uint64_t)received, t[i], ref_ns);
        result = Py_None;
        Py_INCREF(result);
    }
    PyBuffer_Release(&rec);
    PyBuffer_Release(&now);
    return result;
}

static PyMethodDef dcloop_methods[] = {
    {"time_control", time_control, METH_VARARGS, "time_control(rec, received, now, a, b, ref_ns): loop samples of clocks a..b-1"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef dcloop_module = {
    PyModuleDef_HEAD_INIT, "sim_slaves._dcloop", "C speed-up for the emulated DC line's time-control loops", -1,
    dcloop_methods,
};

PyMODINIT_FUNC PyInit__dcloop(void) {
    PyObject *m = PyModule_Create(&dcloop_module);
    if (!m) return NULL;
    /* (field, byte offset) in record order, and the record size: Python compares them with its dtype */
    PyObject *layout = Py_BuildValue(
        "((sn)(sn)(sn)(sn)(sn)(sn)(sn)(sn)(sn)(sn)(sn)(sn)(sn)(sn)(sn)(sn))",
        "anchor_local", offsetof(Clock, anchor_local), "anchor_frac", offsetof(Clock, anchor_frac),
        "anchor_true", offsetof(Clock, anchor_true), "rate", offsetof(Clock, rate),
        "drift_factor", offsetof(Clock, drift_factor), "offset", offsetof(Clock, offset),
        "delay", offsetof(Clock, delay), "last_sample", offsetof(Clock, last_sample),
        "diff", offsetof(Clock, diff), "integral", offsetof(Clock, integral),
        "correction", offsetof(Clock, correction), "weight", offsetof(Clock, weight),
        "tau", offsetof(Clock, tau), "cmax", offsetof(Clock, cmax),
        "has_last", offsetof(Clock, has_last), "primed", offsetof(Clock, primed));
    if (!layout || PyModule_AddObject(m, "layout", layout) < 0 ||
        PyModule_AddIntConstant(m, "record_size", (long)sizeof(Clock)) < 0) {
        Py_XDECREF(layout);
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
