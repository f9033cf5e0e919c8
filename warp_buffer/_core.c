/* warp_buffer._core: the per-message native core of warp_buffer.
 *
 * - The descriptor (warp_buffer.descriptor: the fixed struct LAYOUT "<BBHIQQQQQQQ" + 16 "Q", 192
 *   bytes, little endian) packed from and unpacked into its 27 field values, each checked against
 *   its field's width (a forged or hand-made descriptor may hold anything). The generic CDR codec
 *   is the reference for these bytes in the tests.
 * - Session: a publisher's arena as an importing process maps it (warp_buffer.attach owns the
 *   fetch), and the import of a descriptor: every field checked against the session's geometry,
 *   the block held (a read lock, OFD, on its lock range, counted per block in this process: one
 *   fcntl when the first hold of a block starts, one when its last ends), the delivery
 *   acknowledged, the generation compared.
 * - Hold: one import's token. It keeps its session (the mapping) alive, exposes the block's bytes
 *   read-only through the buffer protocol and DLPack (the capsule's deleter drops its reference),
 *   and ends when it is released or collected, whichever comes first: its deallocation is one C
 *   function under the GIL (no Python lock, no finalizer that can run inside a critical section).
 * - The lease (_core_lease.c): the publisher's side.
 *
 * What has no lock of its own (a session's hold counts, a lease's token count, an arena's peer
 * slots) is changed only under the GIL, by C code that calls no Python meanwhile: the core is for
 * CPython builds with a GIL.
 */
#define PY_SSIZE_T_CLEAN
#define _GNU_SOURCE 1  /* (as pyconfig.h defines it) */
#include <Python.h>
#include <structmember.h>

#include <errno.h>
#include <pthread.h>
#include <fcntl.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>
#include <sys/mman.h>
#include <unistd.h>

#include "_core.h"

pid_t this_pid;

static void refresh_pid(void) {
    this_pid = getpid();
}

/* pid() -> int: this process's pid, kept across forks without a system call per call. */
static PyObject *core_pid(PyObject *module, PyObject *unused) {
    return PyLong_FromLong((long)this_pid);
}

/* warp_buffer.errors classes, set at import (set_error_classes) */
PyObject *DescriptorError, *ExportBoundsError, *StaleBufferError, *ExportError,
    *RecycledBufferError;

/* Raise cls (fallback until it is set) with a message formatted by C's printf (numbers only:
 * "%#llx" and friends, which PyUnicode_FromFormat lacks). */
static PyObject *vraise(PyObject *cls, PyObject *fallback, const char *fmt, va_list args) {
    char text[512];
    vsnprintf(text, sizeof text, fmt, args);
    PyErr_SetString(cls ? cls : fallback, text);
    return NULL;
}

PyObject *raise_as(PyObject *cls, PyObject *fallback, const char *fmt, ...) {
    va_list args;
    va_start(args, fmt);
    vraise(cls, fallback, fmt, args);
    va_end(args);
    return NULL;
}

PyObject *descriptor_error(const char *fmt, ...) {
    va_list args;
    va_start(args, fmt);
    vraise(DescriptorError, PyExc_ValueError, fmt, args);
    va_end(args);
    return NULL;
}


/* The value of field i of values (a tuple or list), checked to fit its width. */
int field_value(PyObject *item, int i, uint64_t *out) {
    if (!PyLong_Check(item)) {
        PyErr_Format(DescriptorError ? DescriptorError : PyExc_ValueError,
                     "descriptor field %s is a %s, not an int", DESC_FIELD_NAMES[i],
                     Py_TYPE(item)->tp_name);
        return -1;
    }
    int overflow = 0;
    unsigned long long v = PyLong_AsUnsignedLongLong(item);
    if (v == (unsigned long long)-1 && PyErr_Occurred()) {
        PyErr_Clear();
        overflow = 1;
    }
    if (overflow || (DESC_FIELD_WIDTHS[i] < 8 && v >> (8 * DESC_FIELD_WIDTHS[i]))) {
        PyErr_Format(DescriptorError ? DescriptorError : PyExc_ValueError,
                     "a descriptor field the wire cannot carry: %s = %R", DESC_FIELD_NAMES[i],
                     item);
        return -1;
    }
    *out = (uint64_t)v;
    return 0;
}

static int fill(PyObject *values, unsigned char *out) {
    PyObject *seq = PySequence_Fast(values, "descriptor values must be a sequence");
    if (seq == NULL)
        return -1;
    if (PySequence_Fast_GET_SIZE(seq) != DESC_FIELDS) {
        descriptor_error("a descriptor has %d fields, not %zd", DESC_FIELDS,
                         PySequence_Fast_GET_SIZE(seq));
        Py_DECREF(seq);
        return -1;
    }
    uint64_t v[DESC_FIELDS];
    for (int i = 0; i < DESC_FIELDS; i++) {
        if (field_value(PySequence_Fast_GET_ITEM(seq, i), i, &v[i]) != 0) {
            Py_DECREF(seq);
            return -1;
        }
    }
    Py_DECREF(seq);
    desc_pack(v, out);
    return 0;
}

/* pack(values) -> bytes: the 192 bytes of a descriptor's 27 field values. */
static PyObject *core_pack(PyObject *module, PyObject *values) {
    PyObject *out = PyBytes_FromStringAndSize(NULL, DESC_BYTES);
    if (out == NULL)
        return NULL;
    if (fill(values, (unsigned char *)PyBytes_AS_STRING(out)) != 0) {
        Py_DECREF(out);
        return NULL;
    }
    return out;
}

/* pack_into(buffer, offset, values): write them at offset of a writable buffer. */
static PyObject *core_pack_into(PyObject *module, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "pack_into(buffer, offset, values)");
        return NULL;
    }
    Py_ssize_t offset = PyLong_AsSsize_t(args[1]);
    if (offset == -1 && PyErr_Occurred())
        return NULL;
    Py_buffer view;
    if (PyObject_GetBuffer(args[0], &view, PyBUF_WRITABLE) != 0)
        return NULL;
    PyObject *result = NULL;
    if (offset < 0 || view.len - offset < DESC_BYTES)
        descriptor_error("no room for a %d-byte descriptor at offset %zd of %zd bytes",
                         DESC_BYTES, offset, view.len);
    else if (fill(args[2], (unsigned char *)view.buf + offset) == 0)
        result = Py_NewRef(Py_None);
    PyBuffer_Release(&view);
    return result;
}

static PyObject *values_tuple(const unsigned char *in) {
    uint64_t v[DESC_FIELDS];
    desc_unpack(in, v);
    PyObject *out = PyTuple_New(DESC_FIELDS);
    if (out == NULL)
        return NULL;
    for (int i = 0; i < DESC_FIELDS; i++) {
        PyObject *item = PyLong_FromUnsignedLongLong(v[i]);
        if (item == NULL) {
            Py_DECREF(out);
            return NULL;
        }
        PyTuple_SET_ITEM(out, i, item);
    }
    return out;
}

/* unpack(data, offset=0) -> tuple: the 27 field values of the descriptor at offset. Without an
 * offset, data must be exactly one descriptor. */
static PyObject *core_unpack(PyObject *module, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs < 1 || nargs > 2) {
        PyErr_SetString(PyExc_TypeError, "unpack(data, offset=0)");
        return NULL;
    }
    Py_ssize_t offset = 0;
    if (nargs == 2) {
        offset = PyLong_AsSsize_t(args[1]);
        if (offset == -1 && PyErr_Occurred())
            return NULL;
    }
    Py_buffer view;
    if (PyObject_GetBuffer(args[0], &view, PyBUF_SIMPLE) != 0)
        return NULL;
    PyObject *result = NULL;
    if (nargs == 1 && view.len != DESC_BYTES)
        descriptor_error("a descriptor is %d bytes, not %zd", DESC_BYTES, view.len);
    else if (offset < 0 || view.len - offset < DESC_BYTES)
        descriptor_error("no %d-byte descriptor at offset %zd of %zd bytes", DESC_BYTES, offset,
                         view.len);
    else
        result = values_tuple((const unsigned char *)view.buf + offset);
    PyBuffer_Release(&view);
    return result;
}

/* set_error_classes(descriptor, bounds, stale, export, recycled): warp_buffer.errors' classes. */
static PyObject *set_error_classes(PyObject *module, PyObject *args) {
    enum { N = 5 };
    PyObject *classes[N];
    if (!PyArg_ParseTuple(args, "OOOOO", &classes[0], &classes[1], &classes[2], &classes[3],
                          &classes[4]))
        return NULL;
    for (int i = 0; i < N; i++) {
        if (!PyType_Check(classes[i]) || !PyType_IsSubtype((PyTypeObject *)classes[i],
                                                           (PyTypeObject *)PyExc_Exception)) {
            PyErr_SetString(PyExc_TypeError, "exception classes");
            return NULL;
        }
    }
    PyObject **slots[N] = {&DescriptorError, &ExportBoundsError, &StaleBufferError, &ExportError,
                           &RecycledBufferError};
    for (int i = 0; i < N; i++) {
        Py_INCREF(classes[i]);
        Py_XSETREF(*slots[i], classes[i]);
    }
    Py_RETURN_NONE;
}

static PyMethodDef core_methods[] = {
    {"pid", core_pid, METH_NOARGS,
     "pid() -> int: this process's pid (kept across forks, no system call)."},
    {"pack", (PyCFunction)core_pack, METH_O,
     "pack(values) -> bytes: a descriptor's 27 field values as its 192 bytes (each checked)."},
    {"pack_into", (PyCFunction)(void (*)(void))core_pack_into, METH_FASTCALL,
     "pack_into(buffer, offset, values): the same, written into a writable buffer."},
    {"unpack", (PyCFunction)(void (*)(void))core_unpack, METH_FASTCALL,
     "unpack(data, offset=0) -> tuple: the 27 field values of the descriptor at offset."},
    {"set_descriptor_type", set_descriptor_type, METH_VARARGS,
     "set_descriptor_type(cls, fields): the message class descriptors are made of."},
    {"make", make_descriptor_py, METH_O,
     "make(values) -> descriptor: a descriptor message of its 27 field values (checked)."},
    {"describe", describe, METH_VARARGS,
     "describe(lease, peer, kind, size, owner_pid, session, device_word=0, handles=None) -> "
     "descriptor: the lease's block exported to the peer and described, in one call."},
    {"check_names", check_names, METH_O,
     "check_names(values): DescriptorError unless the 27 values name an export (checked "
     "before an import attaches to the session they name)."},
    {"sessions_after_fork", sessions_after_fork, METH_NOARGS,
     "In a forked child: every live session's holds move onto a description of its own."},
    {"configure", lease_configure, METH_VARARGS,
     "configure(write_state, complete_write, order_after_write, write_handle_error): the "
     "Python pieces the lease calls (warp_buffer.lease)."},
    {"set_error_classes", set_error_classes, METH_VARARGS,
     "set_error_classes(descriptor, bounds, stale, export, recycled): warp_buffer.errors' "
     "classes."},
    {NULL}
};

static struct PyModuleDef core_module = {
    PyModuleDef_HEAD_INIT, "warp_buffer._core",
    "warp_buffer's per-message native core: the descriptor's fixed layout, imports and holds.",
    -1, core_methods,
};

PyMODINIT_FUNC PyInit__core(void) {
    refresh_pid();
    if (pthread_atfork(NULL, NULL, refresh_pid) != 0) {
        PyErr_SetString(PyExc_RuntimeError, "pthread_atfork failed");
        return NULL;
    }
    if (PyType_Ready(&SessionType) < 0 || PyType_Ready(&HoldType) < 0)
        return NULL;
    PyObject *m = PyModule_Create(&core_module);
    if (m == NULL)
        return NULL;
    if (lease_module_init(m) < 0
            || PyModule_AddObjectRef(m, "Session", (PyObject *)&SessionType) < 0
            || PyModule_AddObjectRef(m, "Hold", (PyObject *)&HoldType) < 0
            || PyModule_AddIntConstant(m, "DESCRIPTOR_BYTES", DESC_BYTES) < 0
            || PyModule_AddIntConstant(m, "DESCRIPTOR_FIELDS", DESC_FIELDS) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
