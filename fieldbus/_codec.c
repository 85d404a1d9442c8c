/* fieldbus._codec: encode/decode the scaled channels of a process image in one call.
 *
 * Optional speed-up for fieldbus.core.pdo.image.DirectionImage; the numpy path
 * does the same work when this module is not built. One row per axis:
 *   row r starts at buf + r * stride; the wire bytes are at the start of the row,
 *   the float64 engineering values at float_offset + 8 * j (column j).
 * encode: raw = a*value + b; NaN keeps the raw value sent last; integers are
 *         rounded (half to even, as numpy.rint) and saturated to [lo, hi]
 *         (64-bit: hi is 2**63 or 2**64 as a double, stored as INT64_MAX or
 *         UINT64_MAX; floats saturate to their largest finite value);
 *         stored little-endian at the column's wire offset.
 * decode: value = c*raw + d.
 * Bit-level columns (x unsigned, y signed; ``bits`` wide from bit ``shift`` of
 * the first byte, little-endian bit order): encoded as integers, a value at or
 * above 2**bits (2**(bits-1) signed) as the largest one, as the numpy bit path;
 * only the entry's bits of the bytes it spans change.
 * An offset of 0 comes as -0.0 (x + -0.0 == x, -0.0 included). The numpy path
 * is the reference: the same bits for every input (tests/unit/test_codec_differential.py).
 * Little-endian hosts only (checked in Python before use).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

/* a*x + b must round twice, as numpy's multiply then add: no fused multiply-add
 * (GCC contracts by default in GNU C mode where the target has FMA, e.g. aarch64). */
#if defined(__clang__)
#pragma STDC FP_CONTRACT OFF
#elif defined(__GNUC__)
#pragma GCC optimize("fp-contract=off")
#endif

typedef struct {
    int32_t wire_offset;
    char type;  /* numpy type char: b B h H i I q Q f d; bit-level: x (unsigned), y (signed) */
    uint8_t shift;  /* x / y: bit of the entry's bit 0 in its first byte (0-7) */
    uint8_t bits;   /* x / y: width (1-64) */
    char pad;
    double a, b, c, d, lo, hi;
} Column;

typedef struct {
    PyObject_HEAD
    Py_buffer buf;
    Py_buffer last;
    Py_ssize_t rows, stride, float_offset, ncols;
    Column *cols;
    int have_buf, have_last;
} ScaledCodec;

static void codec_dealloc(ScaledCodec *self) {
    if (self->have_buf) PyBuffer_Release(&self->buf);
    if (self->have_last) PyBuffer_Release(&self->last);
    PyMem_Free(self->cols);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int codec_init(ScaledCodec *self, PyObject *args, PyObject *kwds) {
    PyObject *buf_obj, *last_obj;
    Py_buffer spec;
    Py_ssize_t rows, stride, float_offset;
    if (!PyArg_ParseTuple(args, "OnnnOy*", &buf_obj, &rows, &stride, &float_offset, &last_obj, &spec))
        return -1;
    int ok = -1;
    if (spec.len % (Py_ssize_t)sizeof(Column) != 0) {
        PyErr_SetString(PyExc_ValueError, "spec length is not a multiple of the column record");
        goto done;
    }
    self->ncols = spec.len / (Py_ssize_t)sizeof(Column);
    if (PyObject_GetBuffer(buf_obj, &self->buf, PyBUF_WRITABLE | PyBUF_C_CONTIGUOUS) < 0) goto done;
    self->have_buf = 1;
    if (PyObject_GetBuffer(last_obj, &self->last, PyBUF_WRITABLE | PyBUF_C_CONTIGUOUS) < 0) goto done;
    self->have_last = 1;
    if (rows < 0 || stride <= 0 || self->buf.len < rows * stride ||
        float_offset + 8 * self->ncols > stride ||
        self->last.len < rows * self->ncols * (Py_ssize_t)sizeof(double)) {
        PyErr_SetString(PyExc_ValueError, "buffer sizes do not match rows, stride and columns");
        goto done;
    }
    self->cols = PyMem_Malloc(spec.len ? (size_t)spec.len : 1);
    if (!self->cols) { PyErr_NoMemory(); goto done; }
    memcpy(self->cols, spec.buf, (size_t)spec.len);
    for (Py_ssize_t j = 0; j < self->ncols; j++) {
        Column *c = &self->cols[j];
        int width;
        switch (c->type) {
            case 'x': case 'y':
                if (c->shift > 7 || c->bits < 1 || c->bits > 64) {
                    PyErr_SetString(PyExc_ValueError, "bit column: shift 0-7 and 1-64 bits");
                    goto done;
                }
                width = (c->shift + c->bits + 7) / 8;
                break;
            case 'b': case 'B': width = 1; break;
            case 'h': case 'H': width = 2; break;
            case 'i': case 'I': case 'f': width = 4; break;
            case 'q': case 'Q': case 'd': case 'l': case 'L': width = 8; break;
            default:
                PyErr_Format(PyExc_ValueError, "unsupported type code '%c'", c->type);
                goto done;
        }
        if (c->wire_offset < 0 || c->wire_offset + width > float_offset) {
            PyErr_SetString(PyExc_ValueError, "column wire offset outside the wire bytes");
            goto done;
        }
    }
    self->rows = rows;
    self->stride = stride;
    self->float_offset = float_offset;
    ok = 0;
done:
    PyBuffer_Release(&spec);
    return ok;
}

static inline double clamp(double v, double lo, double hi) {
    return v < lo ? lo : (v > hi ? hi : v);
}

/* The entry's ``bits`` bits from bit ``shift`` of ``p`` (little-endian bit order), zero-extended. */
static inline uint64_t get_bits(const uint8_t *p, int shift, int bits) {
    uint64_t v = 0;
    int got = 0;  /* entry bits read so far */
    for (int k = 0; got < bits; k++) {
        int lo = k ? 0 : shift;
        int n = 8 - lo < bits - got ? 8 - lo : bits - got;
        uint64_t part = ((uint64_t)p[k] >> lo) & ((1u << n) - 1u);
        v |= part << got;
        got += n;
    }
    return v;
}

/* Write the low ``bits`` bits of ``v`` from bit ``shift`` of ``p``; the other bits are kept. */
static inline void put_bits(uint8_t *p, int shift, int bits, uint64_t v) {
    int put = 0;
    for (int k = 0; put < bits; k++) {
        int lo = k ? 0 : shift;
        int n = 8 - lo < bits - put ? 8 - lo : bits - put;
        uint8_t m = (uint8_t)(((1u << n) - 1u) << lo);
        uint8_t part = (uint8_t)(((v >> put) << lo) & m);
        p[k] = (uint8_t)((p[k] & (uint8_t)~m) | part);
        put += n;
    }
}

static PyObject *codec_encode(ScaledCodec *self, PyObject *Py_UNUSED(ignored)) {
    uint8_t *base = (uint8_t *)self->buf.buf;
    double *last = (double *)self->last.buf;
    for (Py_ssize_t r = 0; r < self->rows; r++) {
        uint8_t *row = base + r * self->stride;
        const double *val = (const double *)(row + self->float_offset);
        double *prev = last + r * self->ncols;
        for (Py_ssize_t j = 0; j < self->ncols; j++) {
            const Column *c = &self->cols[j];
            double v = val[j] * c->a + c->b;
            if (isnan(v)) {
                v = prev[j];
            } else {
                if (c->type != 'f' && c->type != 'd') v = rint(v);
                v = clamp(v, c->lo, c->hi);
                prev[j] = v;
            }
            uint8_t *dst = row + c->wire_offset;
            switch (c->type) {
                case 'x': {  /* v is integral and within [lo, hi]; hi may be one past the largest */
                    uint64_t x = v >= ldexp(1.0, c->bits) ? (c->bits == 64 ? UINT64_MAX : (1ull << c->bits) - 1u)
                                                          : (uint64_t)v;
                    put_bits(dst, c->shift, c->bits, x);
                    break;
                }
                case 'y': {
                    int64_t top = c->bits == 64 ? INT64_MAX : (int64_t)((1ull << (c->bits - 1)) - 1u);
                    int64_t x = v >= ldexp(1.0, c->bits - 1) ? top : (int64_t)v;
                    put_bits(dst, c->shift, c->bits, (uint64_t)x);
                    break;
                }
                case 'b': { int8_t x = (int8_t)v; memcpy(dst, &x, 1); break; }
                case 'B': { uint8_t x = (uint8_t)v; memcpy(dst, &x, 1); break; }
                case 'h': { int16_t x = (int16_t)v; memcpy(dst, &x, 2); break; }
                case 'H': { uint16_t x = (uint16_t)v; memcpy(dst, &x, 2); break; }
                case 'i': { int32_t x = (int32_t)v; memcpy(dst, &x, 4); break; }
                case 'I': { uint32_t x = (uint32_t)v; memcpy(dst, &x, 4); break; }
                case 'q': case 'l': {
                    int64_t x = v >= 9223372036854775807.0 ? INT64_MAX : (int64_t)v;
                    memcpy(dst, &x, 8); break;
                }
                case 'Q': case 'L': {
                    uint64_t x = v >= 18446744073709551615.0 ? UINT64_MAX : (uint64_t)v;
                    memcpy(dst, &x, 8); break;
                }
                case 'f': { float x = (float)v; memcpy(dst, &x, 4); break; }
                case 'd': { memcpy(dst, &v, 8); break; }
            }
        }
    }
    Py_RETURN_NONE;
}

static PyObject *codec_decode(ScaledCodec *self, PyObject *Py_UNUSED(ignored)) {
    uint8_t *base = (uint8_t *)self->buf.buf;
    for (Py_ssize_t r = 0; r < self->rows; r++) {
        uint8_t *row = base + r * self->stride;
        double *val = (double *)(row + self->float_offset);
        for (Py_ssize_t j = 0; j < self->ncols; j++) {
            const Column *c = &self->cols[j];
            const uint8_t *src = row + c->wire_offset;
            double raw = 0.0;
            switch (c->type) {
                case 'x': raw = (double)get_bits(src, c->shift, c->bits); break;
                case 'y': {
                    uint64_t u = get_bits(src, c->shift, c->bits);
                    if (c->bits < 64 && (u >> (c->bits - 1)) & 1u) u |= ~((1ull << c->bits) - 1u);
                    raw = (double)(int64_t)u;
                    break;
                }
                case 'b': { int8_t x; memcpy(&x, src, 1); raw = x; break; }
                case 'B': { uint8_t x; memcpy(&x, src, 1); raw = x; break; }
                case 'h': { int16_t x; memcpy(&x, src, 2); raw = x; break; }
                case 'H': { uint16_t x; memcpy(&x, src, 2); raw = x; break; }
                case 'i': { int32_t x; memcpy(&x, src, 4); raw = x; break; }
                case 'I': { uint32_t x; memcpy(&x, src, 4); raw = x; break; }
                case 'q': case 'l': { int64_t x; memcpy(&x, src, 8); raw = (double)x; break; }
                case 'Q': case 'L': { uint64_t x; memcpy(&x, src, 8); raw = (double)x; break; }
                case 'f': { float x; memcpy(&x, src, 4); raw = x; break; }
                case 'd': { memcpy(&raw, src, 8); break; }
            }
            val[j] = raw * c->c + c->d;
        }
    }
    Py_RETURN_NONE;
}

static PyMethodDef codec_methods[] = {
    {"encode", (PyCFunction)codec_encode, METH_NOARGS, "values -> wire for every scaled column and row"},
    {"decode", (PyCFunction)codec_decode, METH_NOARGS, "wire -> values for every scaled column and row"},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject ScaledCodecType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "fieldbus._codec.ScaledCodec",
    .tp_basicsize = sizeof(ScaledCodec),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "ScaledCodec(buf, rows, stride, float_offset, last, spec): scaled channels of a process image",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)codec_init,
    .tp_dealloc = (destructor)codec_dealloc,
    .tp_methods = codec_methods,
};

/* -- small-array kernels of the cycle: one C call where numpy takes several (fieldbus.platform.kernels) --
 * Each holds its buffers from construction (as ScaledCodec), 1-D or 2-D with any strides. */

typedef struct {
    char *p;
    Py_ssize_t n0, n1, s0, s1, itemsize;
} Grid;

/* ``obj``'s buffer as a grid of at most 2 dimensions (1-D: n1 = 1); 0, or -1 with an exception. */
static int grid_of(PyObject *obj, Py_buffer *view, Grid *g, int writable, Py_ssize_t itemsize) {
    if (PyObject_GetBuffer(obj, view, PyBUF_RECORDS_RO | (writable ? PyBUF_WRITABLE : 0)) < 0) return -1;
    if (view->ndim < 1 || view->ndim > 2 || view->itemsize != itemsize) {
        PyBuffer_Release(view);
        PyErr_Format(PyExc_ValueError, "a 1-D or 2-D buffer of %zd-byte items is needed", itemsize);
        return -1;
    }
    g->p = (char *)view->buf;
    g->itemsize = itemsize;
    g->n0 = view->shape[0];
    g->s0 = view->strides[0];
    g->n1 = view->ndim == 2 ? view->shape[1] : 1;
    g->s1 = view->ndim == 2 ? view->strides[1] : itemsize;
    return 0;
}

static int same_shape(const Grid *a, const Grid *b) {
    if (a->n0 != b->n0 || a->n1 != b->n1) {
        PyErr_SetString(PyExc_ValueError, "buffers of different shapes");
        return 0;
    }
    return 1;
}

#define AT(g, i, j) ((g).p + (i) * (g).s0 + (j) * (g).s1)

/* Window(values, last, lo, hi): clean() is True when every float64 value lies in [lo, hi] (lo / hi
 * None: is finite; NaN never lies in a window), and then copies the values into ``last``; False leaves
 * ``last`` as it was. As numpy's minimum / maximum / not_equal (or isfinite) and copyto. */
typedef struct {
    PyObject_HEAD
    Py_buffer v[4];
    int held;
    Grid x, last, lo, hi;
} Window;

static void window_dealloc(Window *self) {
    for (int k = 0; k < self->held; k++) PyBuffer_Release(&self->v[k]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int window_init(Window *self, PyObject *args, PyObject *kwds) {
    PyObject *x, *last, *lo, *hi;
    if (!PyArg_ParseTuple(args, "OOOO", &x, &last, &lo, &hi)) return -1;
    if ((lo == Py_None) != (hi == Py_None)) {
        PyErr_SetString(PyExc_ValueError, "lo and hi: both or neither");
        return -1;
    }
    PyObject *objs[4] = {x, last, lo, hi};
    Grid *grids[4] = {&self->x, &self->last, &self->lo, &self->hi};
    int n = lo == Py_None ? 2 : 4;
    for (int k = 0; k < n; k++) {
        if (grid_of(objs[k], &self->v[k], grids[k], k == 1, 8) < 0) return -1;
        self->held = k + 1;
        if (k && !same_shape(&self->x, grids[k])) return -1;
    }
    if (n == 2) self->lo.p = self->hi.p = NULL;
    return 0;
}

static PyObject *window_clean(Window *self, PyObject *Py_UNUSED(ignored)) {
    const Grid x = self->x, lo = self->lo, hi = self->hi;
    for (Py_ssize_t i = 0; i < x.n0; i++) {
        for (Py_ssize_t j = 0; j < x.n1; j++) {
            double v;
            memcpy(&v, AT(x, i, j), 8);
            if (lo.p) {
                double a, b;
                memcpy(&a, AT(lo, i, j), 8);
                memcpy(&b, AT(hi, i, j), 8);
                if (!(v >= a && v <= b)) Py_RETURN_FALSE;
            } else if (!isfinite(v)) {
                Py_RETURN_FALSE;
            }
        }
    }
    const Grid last = self->last;
    for (Py_ssize_t i = 0; i < x.n0; i++)
        for (Py_ssize_t j = 0; j < x.n1; j++) memcpy(AT(last, i, j), AT(x, i, j), 8);
    Py_RETURN_TRUE;
}

static PyMethodDef window_methods[] = {
    {"clean", (PyCFunction)window_clean, METH_NOARGS, "every value in its window: copied to last, True"},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject WindowType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "fieldbus._codec.Window",
    .tp_basicsize = sizeof(Window),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Window(values, last, lo, hi): float64 values checked against a window, copied when clean",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)window_init,
    .tp_dealloc = (destructor)window_dealloc,
    .tp_methods = window_methods,
};

/* AnyBits(words, mask): any() is True when a uint16 word has a bit of ``mask`` set. */
typedef struct {
    PyObject_HEAD
    Py_buffer v;
    int held;
    Grid w;
    uint16_t mask;
} AnyBits;

static void anybits_dealloc(AnyBits *self) {
    if (self->held) PyBuffer_Release(&self->v);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int anybits_init(AnyBits *self, PyObject *args, PyObject *kwds) {
    PyObject *w;
    unsigned short mask;
    if (!PyArg_ParseTuple(args, "OH", &w, &mask)) return -1;
    if (grid_of(w, &self->v, &self->w, 0, 2) < 0) return -1;
    self->held = 1;
    self->mask = mask;
    return 0;
}

static PyObject *anybits_any(AnyBits *self, PyObject *Py_UNUSED(ignored)) {
    const Grid w = self->w;
    for (Py_ssize_t i = 0; i < w.n0; i++) {
        for (Py_ssize_t j = 0; j < w.n1; j++) {
            uint16_t u;
            memcpy(&u, AT(w, i, j), 2);
            if (u & self->mask) Py_RETURN_TRUE;
        }
    }
    Py_RETURN_FALSE;
}

static PyMethodDef anybits_methods[] = {
    {"any", (PyCFunction)anybits_any, METH_NOARGS, "a word has a bit of the mask set"},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject AnyBitsType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "fieldbus._codec.AnyBits",
    .tp_basicsize = sizeof(AnyBits),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "AnyBits(words, mask): whether a uint16 word has a bit of mask set",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)anybits_init,
    .tp_dealloc = (destructor)anybits_dealloc,
    .tp_methods = anybits_methods,
};

/* Copy(dst, src): run() copies the bytes of ``src`` into ``dst`` (uint8, the same shape), as np.copyto. */
typedef struct {
    PyObject_HEAD
    Py_buffer v[2];
    int held;
    Grid dst, src;
} Copy;

static void copy_dealloc(Copy *self) {
    for (int k = 0; k < self->held; k++) PyBuffer_Release(&self->v[k]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int copy_init(Copy *self, PyObject *args, PyObject *kwds) {
    PyObject *dst, *src;
    if (!PyArg_ParseTuple(args, "OO", &dst, &src)) return -1;
    if (grid_of(dst, &self->v[0], &self->dst, 1, 1) < 0) return -1;
    self->held = 1;
    if (grid_of(src, &self->v[1], &self->src, 0, 1) < 0) return -1;
    self->held = 2;
    return same_shape(&self->dst, &self->src) ? 0 : -1;
}

static PyObject *copy_run(Copy *self, PyObject *Py_UNUSED(ignored)) {
    const Grid d = self->dst, s = self->src;
    if (d.s1 == 1 && s.s1 == 1) {  /* rows of contiguous bytes (a process image's wire rows) */
        for (Py_ssize_t i = 0; i < d.n0; i++) memmove(d.p + i * d.s0, s.p + i * s.s0, (size_t)d.n1);
    } else {
        for (Py_ssize_t i = 0; i < d.n0; i++)
            for (Py_ssize_t j = 0; j < d.n1; j++) *AT(d, i, j) = *AT(s, i, j);
    }
    Py_RETURN_NONE;
}

static PyMethodDef copy_methods[] = {
    {"run", (PyCFunction)copy_run, METH_NOARGS, "src's bytes into dst"},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject CopyType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "fieldbus._codec.Copy",
    .tp_basicsize = sizeof(Copy),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Copy(dst, src): src's bytes into dst (uint8 arrays of one shape, any strides)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)copy_init,
    .tp_dealloc = (destructor)copy_dealloc,
    .tp_methods = copy_methods,
};

static struct PyModuleDef codec_module = {
    PyModuleDef_HEAD_INIT, "fieldbus._codec", "C speed-up for process-image scaling", -1, NULL,
};

PyMODINIT_FUNC PyInit__codec(void) {
    PyTypeObject *types[] = {&ScaledCodecType, &WindowType, &AnyBitsType, &CopyType};
    const char *names[] = {"ScaledCodec", "Window", "AnyBits", "Copy"};
    for (int k = 0; k < 4; k++)
        if (PyType_Ready(types[k]) < 0) return NULL;
    PyObject *m = PyModule_Create(&codec_module);
    if (!m) return NULL;
    for (int k = 0; k < 4; k++) {
        Py_INCREF(types[k]);
        if (PyModule_AddObject(m, names[k], (PyObject *)types[k]) < 0) {
            Py_DECREF(types[k]);
            Py_DECREF(m);
            return NULL;
        }
    }
    return m;
}
