/* sim_slaves._pdlink: the drive link's gather and scatter (sim_slaves.ethercat.pdplan.DriveLink) in one
 * call per group of drives.
 *
 * Optional speed-up; without it the link does the same with numpy (a take into a structured staging
 * buffer, one cast copy per object). Both functions take the chain's memory (uint8), the memory
 * address of every object of every drive of the group (int64, drives x objects), the drives' bank
 * slots (int64), the objects' PDO types as one byte each ('B' uint8, 'b' int8, 'H' uint16, 'h' int16,
 * 'I' uint32, 'i' int32; little-endian in memory, as EtherCAT) and the bank arrays of the objects
 * (int64, one per object).
 *
 * gather(...): each object's bytes in memory -> its bank array at the drive's slot (sign- or zero-
 * extended, as numpy casts the PDO type to int64).
 * scatter(...): each bank array's value at the drive's slot -> the object's bytes in memory (its low
 * bytes, two's complement, as numpy's unsafe cast from int64 wraps).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

#define MAX_OBJECTS 16

enum { MEMORY, ADDRS, ROWS, KINDS, ARRAYS, NARGS };

typedef struct {
    Py_buffer memory, addrs, rows, arrays[MAX_OBJECTS];
    int held_memory, held_addrs, held_rows, held_arrays;
    Py_ssize_t rows_n, objects;
    const char *kinds;
} Link;

static void release(Link *k) {
    if (k->held_memory) PyBuffer_Release(&k->memory);
    if (k->held_addrs) PyBuffer_Release(&k->addrs);
    if (k->held_rows) PyBuffer_Release(&k->rows);
    for (int i = 0; i < k->held_arrays; i++) PyBuffer_Release(&k->arrays[i]);
}

static int is_int64(const Py_buffer *v) {
    const char *f = v->format ? v->format : "B";
    return v->itemsize == 8 && (strcmp(f, "q") == 0 || (strcmp(f, "l") == 0 && sizeof(long) == 8));
}

static int kind_size(char c) {
    switch (c) {
    case 'B': case 'b': return 1;
    case 'H': case 'h': return 2;
    case 'I': case 'i': return 4;
    default: return 0;
    }
}

/* the arguments as buffers, every address and slot checked against the memory and the arrays */
static int take(Link *k, PyObject *const *args, Py_ssize_t nargs, int write_memory, const char *name) {
    memset(k, 0, sizeof(*k));
    if (nargs != NARGS) {
        PyErr_Format(PyExc_TypeError, "%s: %d arguments, got %zd", name, NARGS, nargs);
        return -1;
    }
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT;
    if (PyObject_GetBuffer(args[MEMORY], &k->memory, flags | (write_memory ? PyBUF_WRITABLE : 0)) < 0) return -1;
    k->held_memory = 1;
    if (PyObject_GetBuffer(args[ADDRS], &k->addrs, flags) < 0) return -1;
    k->held_addrs = 1;
    if (PyObject_GetBuffer(args[ROWS], &k->rows, flags) < 0) return -1;
    k->held_rows = 1;
    if (!PyBytes_Check(args[KINDS]) || !PyTuple_Check(args[ARRAYS])) {
        PyErr_Format(PyExc_TypeError, "%s: kinds must be bytes, arrays a tuple", name);
        return -1;
    }
    k->objects = PyBytes_GET_SIZE(args[KINDS]);
    k->kinds = PyBytes_AS_STRING(args[KINDS]);
    if (k->objects > MAX_OBJECTS || PyTuple_GET_SIZE(args[ARRAYS]) != k->objects) {
        PyErr_Format(PyExc_ValueError, "%s: %zd kinds, %zd arrays (at most %d)", name, k->objects,
                     PyTuple_GET_SIZE(args[ARRAYS]), MAX_OBJECTS);
        return -1;
    }
    if (!is_int64(&k->addrs) || !is_int64(&k->rows)) {
        PyErr_Format(PyExc_ValueError, "%s: addresses and rows must be int64", name);
        return -1;
    }
    k->rows_n = k->rows.len / 8;
    if (k->addrs.len != k->rows_n * k->objects * 8) {
        PyErr_Format(PyExc_ValueError, "%s: %zd addresses for %zd rows of %zd objects", name, k->addrs.len / 8,
                     k->rows_n, k->objects);
        return -1;
    }
    for (Py_ssize_t j = 0; j < k->objects; j++) {
        Py_buffer *v = &k->arrays[j];
        if (PyObject_GetBuffer(PyTuple_GET_ITEM(args[ARRAYS], j), v, flags | (write_memory ? 0 : PyBUF_WRITABLE)) < 0)
            return -1;
        k->held_arrays = (int)j + 1;
        if (!is_int64(v) || !kind_size(k->kinds[j])) {
            PyErr_Format(PyExc_ValueError, "%s: object %zd: an int64 array and a kind of BbHhIi", name, j);
            return -1;
        }
    }
    const int64_t *addrs = k->addrs.buf, *rows = k->rows.buf;
    for (Py_ssize_t r = 0; r < k->rows_n; r++)
        for (Py_ssize_t j = 0; j < k->objects; j++) {
            int64_t at = addrs[r * k->objects + j];
            if (rows[r] < 0 || rows[r] >= k->arrays[j].len / 8 || at < 0 ||
                at + kind_size(k->kinds[j]) > k->memory.len) {
                PyErr_Format(PyExc_IndexError, "%s: row %zd object %zd out of range", name, r, j);
                return -1;
            }
        }
    return 0;
}

static PyObject *gather(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    Link k;
    PyObject *result = NULL;
    if (take(&k, args, nargs, 0, "gather") == 0) {
        const uint8_t *mem = k.memory.buf;
        const int64_t *addrs = k.addrs.buf, *rows = k.rows.buf;
        for (Py_ssize_t r = 0; r < k.rows_n; r++)
            for (Py_ssize_t j = 0; j < k.objects; j++) {
                const uint8_t *p = mem + addrs[r * k.objects + j];
                int64_t v;
                switch (k.kinds[j]) {
                case 'B': v = p[0]; break;
                case 'b': v = (int8_t)p[0]; break;
                case 'H': v = (uint16_t)(p[0] | p[1] << 8); break;
                case 'h': v = (int16_t)(uint16_t)(p[0] | p[1] << 8); break;
                case 'I': v = (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24; break;
                default: v = (int32_t)((uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24);
                }
                ((int64_t *)k.arrays[j].buf)[rows[r]] = v;
            }
        result = Py_NewRef(Py_None);
    }
    release(&k);
    return result;
}

static PyObject *scatter(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    Link k;
    PyObject *result = NULL;
    if (take(&k, args, nargs, 1, "scatter") == 0) {
        uint8_t *mem = k.memory.buf;
        const int64_t *addrs = k.addrs.buf, *rows = k.rows.buf;
        for (Py_ssize_t r = 0; r < k.rows_n; r++)
            for (Py_ssize_t j = 0; j < k.objects; j++) {
                uint8_t *p = mem + addrs[r * k.objects + j];
                uint64_t v = (uint64_t)((const int64_t *)k.arrays[j].buf)[rows[r]];
                int n = kind_size(k.kinds[j]);
                for (int b = 0; b < n; b++) p[b] = (uint8_t)(v >> (8 * b));
            }
        result = Py_NewRef(Py_None);
    }
    release(&k);
    return result;
}

static PyMethodDef pdlink_methods[] = {
    {"gather", (PyCFunction)(void (*)(void))gather, METH_FASTCALL,
     "gather(memory, addrs, rows, kinds, arrays): objects in memory -> the bank's int64 arrays"},
    {"scatter", (PyCFunction)(void (*)(void))scatter, METH_FASTCALL,
     "scatter(memory, addrs, rows, kinds, arrays): the bank's int64 arrays -> objects in memory"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef pdlink_module = {
    PyModuleDef_HEAD_INIT, "sim_slaves._pdlink", "C speed-up for the ESC chain's drive link", -1, pdlink_methods,
};

PyMODINIT_FUNC PyInit__pdlink(void) { return PyModule_Create(&pdlink_module); }
