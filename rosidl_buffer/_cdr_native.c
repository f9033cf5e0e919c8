/* rosidl_buffer._cdr_native: the per-message CDR codec (XCDR1, little endian) in C.
 *
 * A Program is made once per message type (rosidl_buffer/messages/_cdr.py, _native_program) from
 * the same steps as the Python codec: runs of primitives, strings, nested messages, arrays of
 * numbers, strings or messages, and buffer fields. serialize() and deserialize() interpret it.
 *
 * The Python codec stays the reference: wherever a value or an input is not the plain case (a
 * value the C conversion refuses, a truncated or malformed field, a string that is not valid
 * UTF-8), the op hands that one field to its Python field object (the "step"), which writes it
 * or raises its own typed error. The C path only ever takes what the Python path takes, with the
 * same bytes and the same values, so both agree byte for byte and error for error. Every read is
 * bounds-checked before it happens; every write is checked against the output's length (a route
 * callback that changes the message between the sizing and the writing pass cannot overrun it).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <structmember.h>
#include <stdint.h>
#include <string.h>

#if PY_BIG_ENDIAN
#error "the CDR codec assumes a little-endian host (as the Python codec's fast paths do)"
#endif

#if PY_VERSION_HEX < 0x030B0000  /* public since 3.11; Python 3.10 has them under private names */
static inline int PyFloat_Pack4(double x, char *p, int le) {
    return _PyFloat_Pack4(x, (unsigned char *)p, le);
}
static inline int PyFloat_Pack8(double x, char *p, int le) {
    return _PyFloat_Pack8(x, (unsigned char *)p, le);
}
static inline double PyFloat_Unpack4(const char *p, int le) {
    return _PyFloat_Unpack4((const unsigned char *)p, le);
}
static inline double PyFloat_Unpack8(const char *p, int le) {
    return _PyFloat_Unpack8((const unsigned char *)p, le);
}
#endif

#define ORIGIN 4
#define MARKER 0xFFFFFFFFu
#define MARKER2 0x524F5332u

enum { P_BOOL, P_I8, P_U8, P_I16, P_U16, P_I32, P_U32, P_I64, P_U64, P_F32, P_F64, P_COUNT };
static const int WIDTH[P_COUNT] = {1, 1, 1, 2, 2, 4, 4, 8, 8, 4, 8};

enum { OP_RUN, OP_STRING, OP_NESTED, OP_NUMARRAY, OP_STRARRAY, OP_MSGARRAY, OP_BUFFER };

typedef struct { Py_ssize_t off; PyObject *name; int kind; } Prim;

typedef struct Program Program;

typedef struct {
    int code;
    Py_ssize_t off;          /* the field's slot in the message */
    PyObject *name;          /* the field's name */
    PyObject *step;          /* the Python field (or run) object: the reference path */
    PyObject *element;       /* object arrays: step.element */
    int nprims;
    Prim *prims;             /* runs */
    int kind;                /* numeric arrays: element kind */
    Py_ssize_t array_length; /* T[N] */
    int is_sequence;
    Py_ssize_t bound;        /* T[<=N] */
    Py_ssize_t string_bound;
    Program *sub;            /* nested messages */
    PyObject *dtype, *native; /* numeric arrays: wire dtype, dtype of what is read */
    PyObject *descriptors;   /* buffer fields: backend -> its descriptor's Program */
} Op;

struct Program {
    PyObject_HEAD
    PyTypeObject *cls;
    int nops;
    Op *ops;
    int fixed;               /* one run of primitives only */
    Py_ssize_t fixed_size;   /* its size serialized alone */
};

static PyTypeObject ProgramType;

/* ------------------------------------------------------------------ configuration */
static struct {
    int ready;
    PyTypeObject *ndarray, *buffer, *cpu_impl;
    PyObject *frombuffer, *uint8;
    Py_ssize_t buffer_impl_off, cpu_storage_off, cpu_size_off, cpu_dtype_off, cpu_readers_off;
    PyObject *cpu_impls, *judge_cpu, *impls, *impl_base;
    PyObject *read_context, *wrong_type, *name_bytes, *write_array, *pair, *host_bytes;
    PyObject *resolve_descriptor, *descriptor_programs;
    PyObject *DeserializationError, *SerializationError, *DescriptorTooLargeError;
    PyObject *settings;      /* the Python codec's globals: its MAX_BUFFER_DESCRIPTOR_SIZE */
    PyObject *fallback;
    PyObject *s_size, *s_write, *s_read, *s_check, *s_astype, *s_dtype, *s_from,
             *s_get, *s_impl, *s_cast, *s_B;
} G;

static int slot_offset(PyObject *descr, Py_ssize_t *off) {
    if (!PyObject_TypeCheck(descr, &PyMemberDescr_Type)) {
        PyErr_Format(PyExc_TypeError, "expected a slot's member descriptor, got %R", descr);
        return -1;
    }
    PyMemberDef *member = ((PyMemberDescrObject *)descr)->d_member;
    if (member->type != T_OBJECT_EX || (member->flags & READONLY)) {
        PyErr_SetString(PyExc_TypeError, "expected a writable object slot");
        return -1;
    }
    *off = member->offset;
    return 0;
}

static int type_slot(PyTypeObject *type, const char *name, Py_ssize_t *off) {
    PyObject *descr = PyDict_GetItemString(type->tp_dict, name);
    if (descr == NULL) {
        PyErr_Format(PyExc_TypeError, "%s has no slot %s", type->tp_name, name);
        return -1;
    }
    return slot_offset(descr, off);
}

#define SLOT(o, off) (*(PyObject **)((char *)(o) + (off)))

/* The value of a slot (a new reference); an unset slot raises what getattr raises. */
static inline PyObject *get_slot(PyObject *o, Py_ssize_t off, PyObject *name) {
    PyObject *v = SLOT(o, off);
    if (v != NULL) {
        Py_INCREF(v);
        return v;
    }
    return PyObject_GetAttr(o, name);
}

/* Sets a slot (steals v). */
static inline void set_slot(PyObject *o, Py_ssize_t off, PyObject *v) {
    PyObject *old = SLOT(o, off);
    SLOT(o, off) = v;
    Py_XDECREF(old);
}

static inline Py_ssize_t align(Py_ssize_t pos, Py_ssize_t a) {
    return pos + ((-(pos - ORIGIN)) & (a - 1));
}

static inline int is_instance(PyObject *v, PyTypeObject *cls) {
    return Py_TYPE(v) == cls || PyObject_TypeCheck(v, cls);
}

static PyObject *configure(PyObject *self, PyObject *args, PyObject *kwargs) {
    static char *kw[] = {"ndarray", "buffer", "cpu_impl", "frombuffer", "uint8", "cpu_impls",
                         "judge_cpu", "impls", "impl_base", "read_context", "wrong_type",
                         "name_bytes", "write_array", "pair", "host_bytes", "resolve_descriptor",
                         "DeserializationError", "SerializationError",
                         "DescriptorTooLargeError", "settings", NULL};
    PyObject *ndarray, *buffer, *cpu_impl;
    if (G.ready) {
        PyErr_SetString(PyExc_RuntimeError, "configured already");
        return NULL;
    }
    if (!PyArg_ParseTupleAndKeywords(
            args, kwargs, "O!O!O!OOO!OO!OOOOOOOOOOOO!", kw, &PyType_Type, &ndarray, &PyType_Type,
            &buffer, &PyType_Type, &cpu_impl, &G.frombuffer, &G.uint8, &PyDict_Type,
            &G.cpu_impls, &G.judge_cpu, &PyDict_Type, &G.impls, &G.impl_base, &G.read_context,
            &G.wrong_type, &G.name_bytes, &G.write_array, &G.pair, &G.host_bytes,
            &G.resolve_descriptor,
            &G.DeserializationError, &G.SerializationError, &G.DescriptorTooLargeError,
            &PyDict_Type, &G.settings))
        return NULL;
    G.ndarray = (PyTypeObject *)ndarray;
    G.buffer = (PyTypeObject *)buffer;
    G.cpu_impl = (PyTypeObject *)cpu_impl;
    if (type_slot(G.buffer, "_impl", &G.buffer_impl_off) < 0 ||
        type_slot(G.cpu_impl, "_storage", &G.cpu_storage_off) < 0 ||
        type_slot(G.cpu_impl, "_size", &G.cpu_size_off) < 0 ||
        type_slot(G.cpu_impl, "dtype", &G.cpu_dtype_off) < 0 ||
        type_slot(G.cpu_impl, "_readers", &G.cpu_readers_off) < 0)
        return NULL;
    PyObject *keep[] = {ndarray, buffer, cpu_impl, G.frombuffer, G.uint8, G.cpu_impls,
                        G.judge_cpu, G.impls, G.impl_base, G.read_context, G.wrong_type,
                        G.name_bytes, G.write_array, G.pair, G.host_bytes, G.resolve_descriptor,
                        G.DeserializationError, G.SerializationError,
                        G.DescriptorTooLargeError, G.settings};
    for (size_t i = 0; i < sizeof keep / sizeof keep[0]; i++)
        Py_INCREF(keep[i]);
    G.descriptor_programs = PyDict_New();
    if (G.descriptor_programs == NULL)
        return NULL;
    G.ready = 1;
    Py_RETURN_NONE;
}

/* The descriptor size limit, read where the Python codec reads it (its module global). */
static Py_ssize_t max_descriptor(void) {
    PyObject *v = PyDict_GetItemString(G.settings, "MAX_BUFFER_DESCRIPTOR_SIZE");
    if (v == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "MAX_BUFFER_DESCRIPTOR_SIZE is not set");
        return -1;
    }
    return PyLong_AsSsize_t(v);
}

/* ------------------------------------------------------------------ Program */
static void op_clear(Op *op) {
    Py_CLEAR(op->name);
    Py_CLEAR(op->step);
    Py_CLEAR(op->element);
    Py_CLEAR(op->sub);
    Py_CLEAR(op->dtype);
    Py_CLEAR(op->native);
    Py_CLEAR(op->descriptors);
    if (op->prims) {
        for (int i = 0; i < op->nprims; i++)
            Py_CLEAR(op->prims[i].name);
        PyMem_Free(op->prims);
        op->prims = NULL;
    }
}

static int program_traverse(Program *self, visitproc visit, void *arg) {
    Py_VISIT(self->cls);
    for (int i = 0; i < self->nops; i++) {
        Op *op = &self->ops[i];
        Py_VISIT(op->step);
        Py_VISIT(op->element);
        Py_VISIT(op->sub);
        Py_VISIT(op->descriptors);
    }
    return 0;
}

static int program_clear(Program *self) {
    Py_CLEAR(self->cls);
    for (int i = 0; i < self->nops; i++)
        op_clear(&self->ops[i]);
    PyMem_Free(self->ops);
    self->ops = NULL;
    self->nops = 0;
    return 0;
}

static void program_dealloc(Program *self) {
    PyObject_GC_UnTrack(self);
    program_clear(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static Py_ssize_t run_end(const Op *op, Py_ssize_t pos) {
    for (int i = 0; i < op->nprims; i++) {
        int w = WIDTH[op->prims[i].kind];
        pos = align(pos, w) + w;
    }
    return pos;
}

/* A failed parse leaves op holding only what it owns (prims' names, the descriptors dict): the
 * borrowed references PyArg_ParseTuple stored are forgotten (op_clear would release them). They
 * are taken together once the whole op parsed. */
static int disown(Op *op) {
    op->step = op->name = op->element = op->dtype = op->native = NULL;
    return -1;
}

static int parse_op(Op *op, PyObject *spec) {
    PyObject *descr = NULL, *sub = NULL, *prims = NULL;
    int code;
    if (!PyTuple_Check(spec) || PyTuple_GET_SIZE(spec) < 2) {
        PyErr_SetString(PyExc_TypeError, "an op is a tuple (code, step, ...)");
        return -1;
    }
    code = (int)PyLong_AsLong(PyTuple_GET_ITEM(spec, 0));
    if (code == -1 && PyErr_Occurred())
        return -1;
    op->code = code;
    switch (code) {
    case OP_RUN:
        if (!PyArg_ParseTuple(spec, "iOO!", &code, &op->step, &PyTuple_Type, &prims))
            return disown(op);
        op->nprims = (int)PyTuple_GET_SIZE(prims);
        op->prims = PyMem_Calloc(op->nprims ? op->nprims : 1, sizeof(Prim));
        if (op->prims == NULL) {
            PyErr_NoMemory();
            return disown(op);
        }
        for (int i = 0; i < op->nprims; i++) {
            PyObject *d;
            Prim *p = &op->prims[i];
            if (!PyArg_ParseTuple(PyTuple_GET_ITEM(prims, i), "OUi", &d, &p->name, &p->kind)) {
                p->name = NULL;  /* (borrowed, if the parse stored it) */
                return disown(op);
            }
            Py_INCREF(p->name);
            if (p->kind < 0 || p->kind >= P_COUNT) {
                PyErr_SetString(PyExc_ValueError, "unknown primitive kind");
                return disown(op);
            }
            if (slot_offset(d, &p->off) < 0)
                return disown(op);
        }
        break;
    case OP_STRING:
        if (!PyArg_ParseTuple(spec, "iOOUn", &code, &op->step, &descr, &op->name,
                              &op->string_bound))
            return disown(op);
        break;
    case OP_NESTED:
        if (!PyArg_ParseTuple(spec, "iOOUO!", &code, &op->step, &descr, &op->name, &ProgramType,
                              &sub))
            return disown(op);
        break;
    case OP_NUMARRAY:
        if (!PyArg_ParseTuple(spec, "iOOUinpnOO", &code, &op->step, &descr, &op->name, &op->kind,
                              &op->array_length, &op->is_sequence, &op->bound, &op->dtype,
                              &op->native))
            return disown(op);
        if (op->kind < 0 || op->kind >= P_COUNT) {
            PyErr_SetString(PyExc_ValueError, "unknown primitive kind");
            return disown(op);
        }
        break;
    case OP_STRARRAY:
        if (!PyArg_ParseTuple(spec, "iOOUnpnnO", &code, &op->step, &descr, &op->name,
                              &op->array_length, &op->is_sequence, &op->bound, &op->string_bound,
                              &op->element))
            return disown(op);
        break;
    case OP_MSGARRAY:
        if (!PyArg_ParseTuple(spec, "iOOUnpnO!", &code, &op->step, &descr, &op->name,
                              &op->array_length, &op->is_sequence, &op->bound, &ProgramType,
                              &sub))
            return disown(op);
        break;
    case OP_BUFFER:
        if (!PyArg_ParseTuple(spec, "iOOU", &code, &op->step, &descr, &op->name))
            return disown(op);
        op->descriptors = PyDict_New();
        if (op->descriptors == NULL)
            return disown(op);
        break;
    default:
        PyErr_Format(PyExc_ValueError, "unknown op code %d", code);
        return disown(op);
    }
    Py_INCREF(op->step);
    Py_XINCREF(op->name);
    Py_XINCREF(op->element);
    Py_XINCREF(op->dtype);
    Py_XINCREF(op->native);
    if (sub != NULL) {
        Py_INCREF(sub);
        op->sub = (Program *)sub;
    }
    if (descr != NULL && slot_offset(descr, &op->off) < 0)
        return -1;
    return 0;
}

static PyObject *program_new(PyTypeObject *type, PyObject *args, PyObject *kwargs) {
    PyObject *cls, *ops;
    if (!G.ready) {
        PyErr_SetString(PyExc_RuntimeError, "_cdr_native.configure() was not called");
        return NULL;
    }
    if (!PyArg_ParseTuple(args, "O!O!:Program", &PyType_Type, &cls, &PyTuple_Type, &ops))
        return NULL;
    Program *self = (Program *)type->tp_alloc(type, 0);
    if (self == NULL)
        return NULL;
    Py_INCREF(cls);
    self->cls = (PyTypeObject *)cls;
    Py_ssize_t n = PyTuple_GET_SIZE(ops);
    self->ops = PyMem_Calloc(n ? n : 1, sizeof(Op));
    if (self->ops == NULL) {
        Py_DECREF(self);
        return PyErr_NoMemory();
    }
    self->nops = (int)n;
    for (Py_ssize_t i = 0; i < n; i++) {
        if (parse_op(&self->ops[i], PyTuple_GET_ITEM(ops, i)) < 0) {
            Py_DECREF(self);
            return NULL;
        }
    }
    self->fixed = n == 1 && self->ops[0].code == OP_RUN;
    if (self->fixed)
        self->fixed_size = run_end(&self->ops[0], ORIGIN) - ORIGIN;
    return (PyObject *)self;
}

static PyObject *program_get_fixed(Program *self, void *closure) {
    return PyBool_FromLong(self->fixed);
}

static PyGetSetDef program_getset[] = {
    {"fixed", (getter)program_get_fixed, NULL, "one run of primitives only", NULL},
    {NULL},
};

static PyTypeObject ProgramType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "rosidl_buffer._cdr_native.Program",
    .tp_basicsize = sizeof(Program),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
    .tp_doc = "The CDR steps of one message type, interpreted by serialize/deserialize.",
    .tp_new = program_new,
    .tp_dealloc = (destructor)program_dealloc,
    .tp_traverse = (traverseproc)program_traverse,
    .tp_clear = (inquiry)program_clear,
    .tp_getset = program_getset,
};

/* ------------------------------------------------------------------ serialization */
typedef struct {
    PyObject *host;          /* CPU form: the object whose bytes are written (NULL: descriptor) */
    Py_buffer view;          /* its bytes (has_view) */
    int has_view;
    Py_ssize_t nbytes;
    PyObject *name;          /* descriptor form: the backend name (str, or bytes from Python) */
    const char *name_utf8;
    Py_ssize_t name_len;
    PyObject *descriptor;
    Program *program;
} Decision;

typedef struct {
    PyObject *route;         /* top level only */
    Decision *d;
    Py_ssize_t n, cap, next;
    PyObject *out;
    char *buf;
    Py_ssize_t len;
} SCtx;

static void sctx_free(SCtx *c) {
    for (Py_ssize_t i = 0; i < c->n; i++) {
        Decision *d = &c->d[i];
        if (d->has_view)
            PyBuffer_Release(&d->view);
        Py_XDECREF(d->host);
        Py_XDECREF(d->name);
        Py_XDECREF(d->descriptor);
        Py_XDECREF(d->program);
    }
    PyMem_Free(c->d);
    c->d = NULL;
    c->n = c->cap = 0;
}

static Decision *sctx_push(SCtx *c, Py_ssize_t *index) {
    if (c->n == c->cap) {
        Py_ssize_t cap = c->cap ? 2 * c->cap : 4;
        Decision *d = PyMem_Realloc(c->d, cap * sizeof(Decision));
        if (d == NULL) {
            PyErr_NoMemory();
            return NULL;
        }
        c->d = d;
        c->cap = cap;
    }
    *index = c->n;
    Decision *d = &c->d[c->n++];
    memset(d, 0, sizeof *d);
    return d;
}

static Py_ssize_t pos_result(PyObject *r) {
    if (r == NULL)
        return -1;
    Py_ssize_t pos = PyLong_AsSsize_t(r);
    Py_DECREF(r);
    return pos;
}

static Py_ssize_t program_size(Program *p, PyObject *m, Py_ssize_t pos, SCtx *c, int top);

static int check_message(Program *p, PyObject *v) {
    if (is_instance(v, p->cls))
        return 0;
    PyObject *err = PyObject_CallFunctionObjArgs(G.wrong_type, (PyObject *)p->cls, v, NULL);
    if (err != NULL) {
        PyErr_SetObject((PyObject *)Py_TYPE(err), err);
        Py_DECREF(err);
    }
    return -1;
}

/* The size of a string field's value, or the Python field's (which raises for a bad value). */
static Py_ssize_t string_size(PyObject *step, PyObject *v, Py_ssize_t bound, Py_ssize_t pos) {
    if (PyUnicode_CheckExact(v)) {
        Py_ssize_t n;
        if (PyUnicode_AsUTF8AndSize(v, &n) != NULL) {
            if (!bound || n <= bound)
                return align(pos, 4) + 4 + n + 1;
        } else {
            PyErr_Clear();
        }
    }
    PyObject *ppos = PyLong_FromSsize_t(pos);
    if (ppos == NULL)
        return -1;
    PyObject *r = PyObject_CallMethodObjArgs(step, G.s_size, v, ppos, Py_None, NULL);
    Py_DECREF(ppos);
    return pos_result(r);
}

/* The element count of a numeric array value, as the Python field sizes it; -2: ask it. */
static Py_ssize_t numarray_count(PyObject *v) {
    if (PyList_CheckExact(v))
        return PyList_GET_SIZE(v);
    if (Py_TYPE(v) == G.ndarray) {
        Py_buffer view;
        if (PyObject_GetBuffer(v, &view, PyBUF_STRIDES) < 0) {
            PyErr_Clear();
            return -2;
        }
        Py_ssize_t n = view.ndim == 1 ? view.shape[0] : -2;
        PyBuffer_Release(&view);
        return n;
    }
    return -2;
}

/* A descriptor's serialized size on its own (from the origin: what the size limit is about),
 * or -1 with an exception set. */
static Py_ssize_t alone_size(Program *dp, PyObject *descriptor) {
    SCtx alone = {0};
    Py_ssize_t at = program_size(dp, descriptor, ORIGIN, &alone, 0);
    sctx_free(&alone);
    return at < 0 ? -1 : at - ORIGIN;
}

static Py_ssize_t buffer_size(Op *op, PyObject *value, Py_ssize_t pos, SCtx *c, int top) {
    PyObject *buffer = NULL, *impl = NULL, *routed = NULL, *pair = NULL;
    Py_ssize_t result = -1, index;
    if (is_instance(value, G.buffer)) {
        Py_INCREF(value);
        buffer = value;
    } else if ((buffer = PyObject_CallOneArg((PyObject *)G.buffer, value)) == NULL) {
        return -1;
    }
    if (top && c->route != NULL) {
        if ((impl = get_slot(buffer, G.buffer_impl_off, G.s_impl)) == NULL)
            goto done;
        PyObject *kind = (PyObject *)Py_TYPE(impl);
        PyObject *cpu = PyDict_GetItemWithError(G.cpu_impls, kind);  /* borrowed */
        int is_cpu;
        if (cpu == NULL) {
            if (PyErr_Occurred())
                goto done;
            PyObject *judged = PyObject_CallOneArg(G.judge_cpu, kind);
            if (judged == NULL)
                goto done;
            is_cpu = PyObject_IsTrue(judged);
            Py_DECREF(judged);
        } else {
            is_cpu = PyObject_IsTrue(cpu);
        }
        if (is_cpu < 0)
            goto done;
        if (!is_cpu) {
            if ((routed = PyObject_CallOneArg(c->route, buffer)) == NULL)
                goto done;
            if (routed == Py_None)
                Py_CLEAR(routed);
        }
    }
    if (routed == NULL) {  /* the CPU form */
        PyObject *host = NULL;
        Py_ssize_t count = -1;
        Py_CLEAR(impl);
        if ((impl = get_slot(buffer, G.buffer_impl_off, G.s_impl)) == NULL)
            goto done;
        if (Py_TYPE(buffer) == G.buffer && Py_TYPE(impl) == G.cpu_impl &&
            SLOT(impl, G.cpu_readers_off) == Py_None && SLOT(impl, G.cpu_storage_off) != NULL &&
            SLOT(impl, G.cpu_size_off) != NULL && PyLong_CheckExact(SLOT(impl, G.cpu_size_off))) {
            /* Buffer.host_view of untracked CPU storage: its first _size elements */
            count = PyLong_AsSsize_t(SLOT(impl, G.cpu_size_off));
            if (count < 0 && PyErr_Occurred())
                PyErr_Clear();
            host = SLOT(impl, G.cpu_storage_off);
            if (Py_TYPE(host) != G.ndarray || count < 0)
                host = NULL;
            else
                Py_INCREF(host);
        }
        Decision *d = sctx_push(c, &index);
        if (d == NULL) {
            Py_XDECREF(host);
            goto done;
        }
        if (host != NULL) {
            d->host = host;
            if (PyObject_GetBuffer(host, &d->view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) == 0) {
                d->has_view = 1;
                if (d->view.ndim == 1 && d->view.itemsize == 1 && count <= d->view.len) {
                    d->nbytes = count;
                    result = align(pos, 4) + 4 + count;
                    goto done;
                }
                PyBuffer_Release(&d->view);
                d->has_view = 0;
            } else {
                PyErr_Clear();
            }
            Py_CLEAR(d->host);
        }
        /* _cdr._host_bytes(buffer): its contents as the bytes a uint8[] carries */
        host = PyObject_CallOneArg(G.host_bytes, buffer);
        d = &c->d[index];
        if (host == NULL)
            goto done;
        d->host = host;
        if (PyObject_GetBuffer(host, &d->view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) == 0) {
            d->has_view = 1;
            if (!(d->view.ndim == 1 && d->view.itemsize == 1)) {
                PyBuffer_Release(&d->view);
                d->has_view = 0;
            }
        } else {
            PyErr_Clear();
        }
        if (d->has_view) {
            d->nbytes = d->view.len;
        } else {  /* written by the Python codec's _write_array, as the Python path does */
            PyObject *nbytes = PyObject_GetAttrString(host, "nbytes");
            if ((d->nbytes = pos_result(nbytes)) < 0)
                goto done;
        }
        result = align(pos, 4) + 4 + d->nbytes;
        goto done;
    }
    /* the descriptor form */
    PyObject *name, *descriptor;
    if (PyTuple_CheckExact(routed) && PyTuple_GET_SIZE(routed) == 2) {
        Py_INCREF(routed);
        pair = routed;
    } else if ((pair = PyObject_CallOneArg(G.pair, routed)) == NULL) {
        goto done;
    }
    name = PyTuple_GET_ITEM(pair, 0);
    descriptor = PyTuple_GET_ITEM(pair, 1);
    Decision *d = sctx_push(c, &index);
    if (d == NULL)
        goto done;
    if (PyUnicode_CheckExact(name) &&
        (d->name_utf8 = PyUnicode_AsUTF8AndSize(name, &d->name_len)) != NULL) {
        Py_INCREF(name);
        d->name = name;
    } else {
        PyErr_Clear();
        PyObject *encoded = PyObject_CallFunctionObjArgs(G.name_bytes, name, op->name, NULL);
        d = &c->d[index];
        if (encoded == NULL)
            goto done;
        if (!PyBytes_Check(encoded) || PyBytes_GET_SIZE(encoded) < 1) {
            Py_DECREF(encoded);
            PyErr_SetString(PyExc_TypeError, "backend name bytes expected");
            goto done;
        }
        d->name = encoded;
        d->name_utf8 = PyBytes_AS_STRING(encoded);
        d->name_len = PyBytes_GET_SIZE(encoded) - 1;  /* with its NUL */
    }
    Py_INCREF(descriptor);
    d->descriptor = descriptor;
    PyObject *program = PyDict_GetItemWithError(G.descriptor_programs,
                                                (PyObject *)Py_TYPE(descriptor));
    if (program == NULL) {
        if (PyErr_Occurred())
            goto done;
        program = PyObject_CallOneArg(G.resolve_descriptor, descriptor);
        d = &c->d[index];
        if (program == NULL)
            goto done;
        if (!PyObject_TypeCheck(program, &ProgramType)) {
            Py_DECREF(program);
            PyErr_SetString(PyExc_TypeError, "resolve_descriptor must return a Program");
            goto done;
        }
        if (PyDict_SetItem(G.descriptor_programs, (PyObject *)Py_TYPE(descriptor), program) < 0) {
            Py_DECREF(program);
            goto done;
        }
    } else {
        Py_INCREF(program);
    }
    d->program = (Program *)program;
    Program *dp = d->program;
    if (check_message(dp, descriptor) < 0)
        goto done;
    pos = align(pos, 4) + 12 + d->name_len + 1;
    Py_ssize_t nbytes, end;
    if (dp->fixed) {
        nbytes = dp->fixed_size;
        end = run_end(&dp->ops[0], pos);
    } else {
        if ((nbytes = alone_size(dp, descriptor)) < 0)
            goto done;
        if ((end = program_size(dp, descriptor, pos, c, 0)) < 0)
            goto done;
        d = &c->d[index];
    }
    Py_ssize_t limit = max_descriptor();
    if (limit < 0 && PyErr_Occurred())
        goto done;
    if (nbytes > limit) {
        PyErr_Format(G.DescriptorTooLargeError,
                     "field %R: descriptor of backend %R serializes to %zd bytes, over the "
                     "%zd-byte limit", op->name, name, nbytes, limit);
        goto done;
    }
    result = end;
done:
    Py_XDECREF(buffer);
    Py_XDECREF(impl);
    Py_XDECREF(routed);
    Py_XDECREF(pair);
    return result;
}

static Py_ssize_t program_size(Program *p, PyObject *m, Py_ssize_t pos, SCtx *c, int top) {
    if (check_message(p, m) < 0)
        return -1;
    for (int i = 0; i < p->nops && pos >= 0; i++) {
        Op *op = &p->ops[i];
        PyObject *v;
        if (op->code == OP_RUN) {
            pos = run_end(op, pos);
            continue;
        }
        if ((v = get_slot(m, op->off, op->name)) == NULL)
            return -1;
        switch (op->code) {
        case OP_STRING:
            pos = string_size(op->step, v, op->string_bound, pos);
            break;
        case OP_NESTED:
            pos = program_size(op->sub, v, pos, c, 0);
            break;
        case OP_NUMARRAY: {
            Py_ssize_t n = numarray_count(v);
            if (n == -2) {
                PyObject *ppos = PyLong_FromSsize_t(pos);
                if (ppos == NULL) {
                    pos = -1;
                    break;
                }
                pos = pos_result(PyObject_CallMethodObjArgs(op->step, G.s_size, v, ppos, Py_None,
                                                            NULL));
                Py_DECREF(ppos);
                break;
            }
            int w = WIDTH[op->kind];
            if (op->is_sequence)
                pos = align(pos, 4) + 4;
            if (n)
                pos = align(pos, w) + n * w;
            break;
        }
        case OP_STRARRAY:
        case OP_MSGARRAY: {
            Py_ssize_t n = (PyList_Check(v) || PyTuple_Check(v)) ? Py_SIZE(v) : -1;
            if (n < 0 || (op->array_length && n != op->array_length) ||
                (op->bound && n > op->bound)) {
                PyObject *r = PyObject_CallMethodOneArg(op->step, G.s_check, v);
                if (r == NULL) {
                    pos = -1;
                    break;
                }
                Py_DECREF(r);
                PyErr_SetString(G.SerializationError, "object array check disagreed");
                pos = -1;
                break;
            }
            if (op->is_sequence)
                pos = align(pos, 4) + 4;
            for (Py_ssize_t k = 0; pos >= 0 && k < Py_SIZE(v); k++) {
                PyObject *item = PyList_Check(v) ? PyList_GET_ITEM(v, k) : PyTuple_GET_ITEM(v, k);
                Py_INCREF(item);
                if (op->code == OP_STRARRAY)
                    pos = string_size(op->element, item, op->string_bound, pos);
                else
                    pos = program_size(op->sub, item, pos, c, 0);
                Py_DECREF(item);
            }
            break;
        }
        case OP_BUFFER:
            pos = buffer_size(op, v, pos, c, top);
            break;
        }
        Py_DECREF(v);
    }
    return pos;
}

static int changed(void) {
    PyErr_SetString(G.SerializationError,
                    "the message changed while it was serialized (a route callback?)");
    return -1;
}

static inline int room(SCtx *c, Py_ssize_t pos, Py_ssize_t n) {
    if (pos < 0 || n < 0 || pos > c->len || n > c->len - pos)
        return changed();
    return 0;
}

/* Pads to a and checks that n bytes fit after it; returns the aligned position or -1. */
static inline Py_ssize_t pad(SCtx *c, Py_ssize_t pos, Py_ssize_t a, Py_ssize_t n) {
    Py_ssize_t at = align(pos, a);
    if (room(c, pos, at - pos + n) < 0)
        return -1;
    memset(c->buf + pos, 0, at - pos);
    return at;
}

static inline void put_u32(char *p, uint32_t v) { memcpy(p, &v, 4); }

static void refresh(SCtx *c) {
    c->buf = PyByteArray_AS_STRING(c->out);
    c->len = PyByteArray_GET_SIZE(c->out);
}

/* step.write(value, out, pos, []): the Python field's write (its typed error). */
static Py_ssize_t delegate_write(SCtx *c, PyObject *step, PyObject *value, Py_ssize_t pos) {
    PyObject *ppos = PyLong_FromSsize_t(pos), *decisions = PyList_New(0);
    Py_ssize_t r = -1;
    if (ppos != NULL && decisions != NULL)
        r = pos_result(PyObject_CallMethodObjArgs(step, G.s_write, value, c->out, ppos, decisions,
                                                  NULL));
    Py_XDECREF(ppos);
    Py_XDECREF(decisions);
    refresh(c);
    return r;
}

/* One primitive into p (its width is there); 0, or -1 with no error set when the C conversion
 * refuses the value (the Python field then writes it, or raises its error). */
static int put_primitive(char *p, int kind, PyObject *v) {
    if (kind == P_BOOL) {
        int t = PyObject_IsTrue(v);
        if (t < 0) {
            PyErr_Clear();
            return -1;
        }
        *p = (char)t;
        return 0;
    }
    if (kind == P_F32 || kind == P_F64) {
        double x = PyFloat_AsDouble(v);
        if (x == -1.0 && PyErr_Occurred()) {
            PyErr_Clear();
            return -1;
        }
        if ((kind == P_F32 ? PyFloat_Pack4(x, p, 1) : PyFloat_Pack8(x, p, 1)) < 0) {
            PyErr_Clear();
            return -1;
        }
        return 0;
    }
    PyObject *index;
    if (PyLong_Check(v)) {
        Py_INCREF(v);
        index = v;
    } else if (PyIndex_Check(v)) {
        if ((index = PyNumber_Index(v)) == NULL) {
            PyErr_Clear();
            return -1;
        }
    } else {
        return -1;
    }
    int overflow = 0;
    if (kind == P_U64) {
        unsigned long long u = PyLong_AsUnsignedLongLong(index);
        Py_DECREF(index);
        if (u == (unsigned long long)-1 && PyErr_Occurred()) {
            PyErr_Clear();
            return -1;
        }
        memcpy(p, &u, 8);
        return 0;
    }
    long long x = PyLong_AsLongLongAndOverflow(index, &overflow);
    Py_DECREF(index);
    if (overflow || (x == -1 && PyErr_Occurred())) {
        PyErr_Clear();
        return -1;
    }
    switch (kind) {
    case P_I8: if (x < INT8_MIN || x > INT8_MAX) return -1; { int8_t y = (int8_t)x; memcpy(p, &y, 1); } break;
    case P_U8: if (x < 0 || x > UINT8_MAX) return -1; { uint8_t y = (uint8_t)x; memcpy(p, &y, 1); } break;
    case P_I16: if (x < INT16_MIN || x > INT16_MAX) return -1; { int16_t y = (int16_t)x; memcpy(p, &y, 2); } break;
    case P_U16: if (x < 0 || x > UINT16_MAX) return -1; { uint16_t y = (uint16_t)x; memcpy(p, &y, 2); } break;
    case P_I32: if (x < INT32_MIN || x > INT32_MAX) return -1; { int32_t y = (int32_t)x; memcpy(p, &y, 4); } break;
    case P_U32: if (x < 0 || x > UINT32_MAX) return -1; { uint32_t y = (uint32_t)x; memcpy(p, &y, 4); } break;
    case P_I64: { int64_t y = (int64_t)x; memcpy(p, &y, 8); } break;
    default: return -1;
    }
    return 0;
}

static Py_ssize_t string_write(SCtx *c, PyObject *step, PyObject *v, Py_ssize_t bound,
                               Py_ssize_t pos) {
    if (PyUnicode_CheckExact(v)) {
        Py_ssize_t n;
        const char *s = PyUnicode_AsUTF8AndSize(v, &n);
        if (s != NULL && (!bound || n <= bound)) {
            if ((pos = pad(c, pos, 4, 4 + n + 1)) < 0)
                return -1;
            put_u32(c->buf + pos, (uint32_t)(n + 1));
            memcpy(c->buf + pos + 4, s, n);
            c->buf[pos + 4 + n] = 0;
            return pos + 4 + n + 1;
        }
        PyErr_Clear();
    }
    return delegate_write(c, step, v, pos);
}

static int format_kind_ok(const char *format, int kind) {
    if (format == NULL)
        return kind == P_U8;
    if (*format == '<' || *format == '=' || *format == '@')
        format++;
    if (format[0] == 0 || format[1] != 0)
        return 0;
    switch (kind) {
    case P_BOOL: return *format == '?';
    case P_I8: case P_I16: case P_I32: case P_I64: return strchr("bhilq", *format) != NULL;
    case P_U8: case P_U16: case P_U32: case P_U64: return strchr("BHILQ", *format) != NULL;
    case P_F32: case P_F64: return *format == 'f' || *format == 'd';
    }
    return 0;
}

static Py_ssize_t numarray_write(SCtx *c, Op *op, PyObject *v, Py_ssize_t pos) {
    int w = WIDTH[op->kind];
    if (Py_TYPE(v) == G.ndarray) {
        Py_buffer view;
        if (PyObject_GetBuffer(v, &view, PyBUF_RECORDS_RO) == 0) {
            Py_ssize_t n = view.ndim == 1 ? view.shape[0] : -1;
            int ok = n >= 0 && view.itemsize == w && format_kind_ok(view.format, op->kind) &&
                     PyBuffer_IsContiguous(&view, 'C') &&
                     (!op->array_length || n == op->array_length) && (!op->bound || n <= op->bound);
            if (ok) {
                if (op->is_sequence) {
                    if ((pos = pad(c, pos, 4, 4)) < 0)
                        goto fail;
                    put_u32(c->buf + pos, (uint32_t)n);
                    pos += 4;
                }
                if (n) {
                    if ((pos = pad(c, pos, w, n * w)) < 0)
                        goto fail;
                    memcpy(c->buf + pos, view.buf, n * w);
                    pos += n * w;
                }
                PyBuffer_Release(&view);
                return pos;
            fail:
                PyBuffer_Release(&view);
                return -1;
            }
            PyBuffer_Release(&view);
        } else {
            PyErr_Clear();
        }
    }
    return delegate_write(c, op->step, v, pos);
}

static Py_ssize_t program_write(Program *p, PyObject *m, Py_ssize_t pos, SCtx *c);

static Py_ssize_t buffer_write(SCtx *c, Op *op, Py_ssize_t pos) {
    if (c->next >= c->n)
        return changed();
    Decision *d = &c->d[c->next++];
    if (d->host != NULL) {
        if (!d->has_view) {
            PyObject *ppos = PyLong_FromSsize_t(pos);
            if (ppos == NULL)
                return -1;
            PyObject *one = PyLong_FromLong(1);
            pos = pos_result(PyObject_CallFunctionObjArgs(G.write_array, d->host, c->out, ppos,
                                                          Py_True, one, NULL));
            Py_DECREF(ppos);
            Py_XDECREF(one);
            refresh(c);
            return pos;
        }
        if (d->nbytes > UINT32_MAX) {
            PyErr_Format(G.SerializationError, "field %R: %zd bytes exceed a CDR sequence",
                         op->name, d->nbytes);
            return -1;
        }
        if ((pos = pad(c, pos, 4, 4 + d->nbytes)) < 0)
            return -1;
        put_u32(c->buf + pos, (uint32_t)d->nbytes);
        memcpy(c->buf + pos + 4, d->view.buf, d->nbytes);
        return pos + 4 + d->nbytes;
    }
    if ((pos = pad(c, pos, 4, 12 + d->name_len + 1)) < 0)
        return -1;
    put_u32(c->buf + pos, MARKER);
    put_u32(c->buf + pos + 4, MARKER2);
    put_u32(c->buf + pos + 8, (uint32_t)(d->name_len + 1));
    memcpy(c->buf + pos + 12, d->name_utf8, d->name_len);
    c->buf[pos + 12 + d->name_len] = 0;
    pos += 12 + d->name_len + 1;
    return program_write(d->program, d->descriptor, pos, c);
}

static Py_ssize_t program_write(Program *p, PyObject *m, Py_ssize_t pos, SCtx *c) {
    if (!is_instance(m, p->cls))
        return changed();
    for (int i = 0; i < p->nops && pos >= 0; i++) {
        Op *op = &p->ops[i];
        if (op->code == OP_RUN) {
            Py_ssize_t start = pos;
            int k;
            for (k = 0; k < op->nprims; k++) {
                Prim *prim = &op->prims[k];
                int w = WIDTH[prim->kind];
                PyObject *v = get_slot(m, prim->off, prim->name);
                if (v == NULL)
                    return -1;
                if ((pos = pad(c, pos, w, w)) < 0) {
                    Py_DECREF(v);
                    return -1;
                }
                int bad = put_primitive(c->buf + pos, prim->kind, v);
                Py_DECREF(v);
                if (bad)
                    break;
                pos += w;
            }
            if (k < op->nprims)
                pos = delegate_write(c, op->step, m, start);
            continue;
        }
        if (op->code == OP_BUFFER) {
            pos = buffer_write(c, op, pos);
            continue;
        }
        PyObject *v = get_slot(m, op->off, op->name);
        if (v == NULL)
            return -1;
        switch (op->code) {
        case OP_STRING:
            pos = string_write(c, op->step, v, op->string_bound, pos);
            break;
        case OP_NESTED:
            pos = program_write(op->sub, v, pos, c);
            break;
        case OP_NUMARRAY:
            pos = numarray_write(c, op, v, pos);
            break;
        case OP_STRARRAY:
        case OP_MSGARRAY:
            if (!(PyList_Check(v) || PyTuple_Check(v))) {
                pos = changed();
                break;
            }
            if (op->is_sequence) {
                if ((pos = pad(c, pos, 4, 4)) < 0)
                    break;
                put_u32(c->buf + pos, (uint32_t)Py_SIZE(v));
                pos += 4;
            }
            for (Py_ssize_t k = 0; pos >= 0 && k < Py_SIZE(v); k++) {
                PyObject *item = PyList_Check(v) ? PyList_GET_ITEM(v, k) : PyTuple_GET_ITEM(v, k);
                Py_INCREF(item);
                if (op->code == OP_STRARRAY)
                    pos = string_write(c, op->element, item, op->string_bound, pos);
                else
                    pos = program_write(op->sub, item, pos, c);
                Py_DECREF(item);
            }
            break;
        }
        Py_DECREF(v);
    }
    return pos;
}

/* serialize(program, message, route, out) -> bytearray */
static PyObject *serialize(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 4 || !PyObject_TypeCheck(args[0], &ProgramType)) {
        PyErr_SetString(PyExc_TypeError, "serialize(program, message, route, out)");
        return NULL;
    }
    Program *p = (Program *)args[0];
    PyObject *m = args[1], *out = args[3];
    SCtx c = {0};
    c.route = args[2] == Py_None ? NULL : args[2];
    Py_ssize_t end = program_size(p, m, ORIGIN, &c, 1);
    if (end < 0)
        goto fail;
    if (out != Py_None && !PyByteArray_Check(out)) {
        PyErr_Format(PyExc_TypeError, "out must be a bytearray, not %.100s",
                     Py_TYPE(out)->tp_name);
        goto fail;
    }
    if (out == Py_None || PyByteArray_GET_SIZE(out) != end) {
        if ((out = PyByteArray_FromStringAndSize(NULL, end)) == NULL)
            goto fail;
    } else {
        Py_INCREF(out);
    }
    c.out = out;
    /* An export held through the write pass: code it runs (a value's __index__, a route) cannot
     * resize out under c.buf (BufferError, as on the Python path). */
    Py_buffer hold;
    if (PyObject_GetBuffer(out, &hold, PyBUF_WRITABLE) < 0) {
        Py_DECREF(out);
        goto fail;
    }
    refresh(&c);
    memcpy(c.buf, "\x00\x01\x00\x00", ORIGIN);
    Py_ssize_t written = program_write(p, m, ORIGIN, &c);
    PyBuffer_Release(&hold);
    if (written != end) {  /* short of the sized end: a value changed in between */
        if (written >= 0)
            changed();
        Py_DECREF(out);
        goto fail;
    }
    sctx_free(&c);
    return out;
fail:
    sctx_free(&c);
    return NULL;
}

/* ------------------------------------------------------------------ deserialization */
typedef struct {
    const unsigned char *data;
    Py_ssize_t len;
    PyObject *owner, *view;
    PyObject *backends, *endpoint_info;
    PyObject *ctx[2];  /* the Python _ReadContext (nested, top level), made on first need */
} RCtx;

static PyObject *read_context(RCtx *c, int top) {
    if (c->ctx[top] == NULL) {
        if (c->view == NULL) {
            PyObject *view = PyMemoryView_FromObject(c->owner);
            if (view == NULL)
                return NULL;
            if (!PyBytes_Check(c->owner)) {
                PyObject *cast = PyObject_CallMethodOneArg(view, G.s_cast, G.s_B);
                Py_DECREF(view);
                if (cast == NULL)
                    return NULL;
                view = cast;
            }
            c->view = view;
        }
        c->ctx[top] = PyObject_CallFunctionObjArgs(G.read_context, c->view, c->owner,
                                                   c->backends, c->endpoint_info,
                                                   top ? Py_True : Py_False, NULL);
    }
    return c->ctx[top];
}

/* step.read(ctx, pos) -> (value, pos): the Python field's read, which raises its typed error. */
static PyObject *delegate_read(RCtx *c, PyObject *step, Py_ssize_t *pos, int top) {
    PyObject *ctx = read_context(c, top), *ppos, *r;
    if (ctx == NULL || (ppos = PyLong_FromSsize_t(*pos)) == NULL)
        return NULL;
    r = PyObject_CallMethodObjArgs(step, G.s_read, ctx, ppos, NULL);
    Py_DECREF(ppos);
    if (r == NULL)
        return NULL;
    if (!PyTuple_Check(r) || PyTuple_GET_SIZE(r) != 2 ||
        (*pos = PyLong_AsSsize_t(PyTuple_GET_ITEM(r, 1))) < 0) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_TypeError, "a field's read returns (value, pos)");
        Py_DECREF(r);
        return NULL;
    }
    PyObject *value = PyTuple_GET_ITEM(r, 0);
    Py_INCREF(value);
    Py_DECREF(r);
    return value;
}

static inline uint32_t get_u32(const unsigned char *p) {
    uint32_t v;
    memcpy(&v, p, 4);
    return v;
}

static PyObject *get_primitive(const unsigned char *p, int kind) {
    switch (kind) {
    case P_BOOL: return PyBool_FromLong(*p != 0);
    case P_I8: return PyLong_FromLong((int8_t)*p);
    case P_U8: return PyLong_FromLong(*p);
    case P_I16: { int16_t v; memcpy(&v, p, 2); return PyLong_FromLong(v); }
    case P_U16: { uint16_t v; memcpy(&v, p, 2); return PyLong_FromLong(v); }
    case P_I32: { int32_t v; memcpy(&v, p, 4); return PyLong_FromLong(v); }
    case P_U32: { uint32_t v; memcpy(&v, p, 4); return PyLong_FromUnsignedLong(v); }
    case P_I64: { int64_t v; memcpy(&v, p, 8); return PyLong_FromLongLong(v); }
    case P_U64: { uint64_t v; memcpy(&v, p, 8); return PyLong_FromUnsignedLongLong(v); }
    case P_F32: { double x = PyFloat_Unpack4((const char *)p, 1);
                  return x == -1.0 && PyErr_Occurred() ? NULL : PyFloat_FromDouble(x); }
    case P_F64: { double x = PyFloat_Unpack8((const char *)p, 1);
                  return x == -1.0 && PyErr_Occurred() ? NULL : PyFloat_FromDouble(x); }
    }
    PyErr_SetString(PyExc_SystemError, "unknown primitive kind");
    return NULL;
}

/* A plain string at pos (NULL without an error: not the plain case, ask the Python field). */
static PyObject *string_read(RCtx *c, Py_ssize_t *pos, Py_ssize_t bound) {
    Py_ssize_t p = align(*pos, 4);
    if (p > c->len - 4)
        return NULL;
    uint32_t n = get_u32(c->data + p);
    p += 4;
    if (n == 0 || n > (uint64_t)(c->len - p) || c->data[p + n - 1] != 0 ||
        (bound && (Py_ssize_t)n - 1 > bound))
        return NULL;
    PyObject *s = PyUnicode_DecodeUTF8((const char *)c->data + p, (Py_ssize_t)n - 1, "strict");
    if (s == NULL) {
        PyErr_Clear();
        return NULL;
    }
    *pos = p + n;
    return s;
}

static PyObject *new_buffer(PyObject *impl) {
    PyObject *buffer = G.buffer->tp_alloc(G.buffer, 0);
    if (buffer == NULL) {
        Py_DECREF(impl);
        return NULL;
    }
    set_slot(buffer, G.buffer_impl_off, impl);
    return buffer;
}

/* CpuBufferImpl.wrap(np.frombuffer(owner, uint8, n, at)) as a Buffer */
static PyObject *cpu_buffer(RCtx *c, Py_ssize_t at, Py_ssize_t n) {
    PyObject *args[4] = {c->owner, G.uint8, NULL, NULL};
    PyObject *array = NULL, *impl = NULL, *dtype = NULL, *size = NULL;
    if ((args[2] = PyLong_FromSsize_t(n)) == NULL || (args[3] = PyLong_FromSsize_t(at)) == NULL)
        goto fail;
    if ((array = PyObject_Vectorcall(G.frombuffer, args, 4, NULL)) == NULL)
        goto fail;
    if ((dtype = PyObject_GetAttr(array, G.s_dtype)) == NULL ||
        (size = PyLong_FromSsize_t(n)) == NULL)
        goto fail;
    if ((impl = G.cpu_impl->tp_alloc(G.cpu_impl, 0)) == NULL)
        goto fail;
    Py_INCREF(Py_None);
    set_slot(impl, G.cpu_readers_off, Py_None);
    set_slot(impl, G.cpu_dtype_off, dtype);
    set_slot(impl, G.cpu_storage_off, array);
    set_slot(impl, G.cpu_size_off, size);
    Py_DECREF(args[2]);
    Py_DECREF(args[3]);
    return new_buffer(impl);
fail:
    Py_XDECREF(args[2]);
    Py_XDECREF(args[3]);
    Py_XDECREF(array);
    Py_XDECREF(dtype);
    Py_XDECREF(size);
    return NULL;
}

static PyObject *program_read(Program *p, RCtx *c, Py_ssize_t *pos, int top);

/* The descriptor form at q (after the three words), name of `length` bytes; NULL without an
 * error: not the plain case (the Python field reads the whole field again, nothing was done). */
static PyObject *descriptor_read(Op *op, RCtx *c, Py_ssize_t *pos, Py_ssize_t q, uint32_t length) {
    PyObject *name = NULL, *backend = NULL, *program = NULL, *descriptor = NULL, *impl = NULL;
    PyObject *result = NULL;
    if (c->data[q + length - 1] != 0)
        return NULL;
    if ((name = PyUnicode_DecodeUTF8((const char *)c->data + q, length - 1, "strict")) == NULL) {
        PyErr_Clear();
        return NULL;
    }
    q += length;
    if (c->backends == Py_None)
        goto plain;
    int truth = PyObject_IsTrue(c->backends);
    if (truth < 0)
        goto fail;
    if (!truth)
        goto plain;
    if (PyDict_CheckExact(c->backends)) {
        backend = PyDict_GetItemWithError(c->backends, name);
        if (backend == NULL) {
            if (PyErr_Occurred())
                goto fail;
            goto plain;
        }
        Py_INCREF(backend);
    } else if ((backend = PyObject_CallMethodOneArg(c->backends, G.s_get, name)) == NULL) {
        goto fail;
    }
    if (backend == Py_None)
        goto plain;
    if ((program = PyDict_GetItemWithError(op->descriptors, backend)) == NULL) {
        if (PyErr_Occurred())
            goto fail;
        /* (the Python field's own cache and lookup: _BufferField._descriptor_types) */
        program = PyObject_CallMethod(op->step, "_native_descriptor_program", "O", backend);
        if (program == NULL)
            goto fail;
        if (!PyObject_TypeCheck(program, &ProgramType)) {
            PyErr_SetString(PyExc_TypeError, "_native_descriptor_program must return a Program");
            goto fail;
        }
        if (PyDict_SetItem(op->descriptors, backend, program) < 0)
            goto fail;
    } else {
        Py_INCREF(program);
    }
    Program *dp = (Program *)program;
    Py_ssize_t nbytes;
    if (dp->fixed) {
        if (run_end(&dp->ops[0], q) > c->len)
            goto plain;
        if ((descriptor = program_read(dp, c, &q, 1)) == NULL)
            goto fail;
        nbytes = dp->fixed_size;
    } else {
        if ((descriptor = program_read(dp, c, &q, 1)) == NULL)
            goto fail;
        if ((nbytes = alone_size(dp, descriptor)) < 0)
            goto fail;
    }
    Py_ssize_t limit = max_descriptor();
    if (limit < 0 && PyErr_Occurred())
        goto fail;
    if (nbytes > limit || c->endpoint_info == Py_None)
        goto plain;
    impl = PyObject_CallMethodObjArgs(backend, G.s_from, descriptor, c->endpoint_info, NULL);
    if (impl == NULL)
        goto fail;
    PyObject *valid = PyDict_GetItemWithError(G.impls, (PyObject *)Py_TYPE(impl));
    int ok;
    if (valid == NULL) {
        if (PyErr_Occurred())
            goto fail;
        ok = PyObject_IsSubclass((PyObject *)Py_TYPE(impl), G.impl_base);
        if (ok < 0 || PyDict_SetItem(G.impls, (PyObject *)Py_TYPE(impl),
                                     ok ? Py_True : Py_False) < 0)
            goto fail;
    } else {
        ok = valid == Py_True;
    }
    if (!ok) {
        PyErr_Format(G.DeserializationError,
                     "field %R: backend %R returned %s, not a BufferImplBase", op->name, name,
                     _PyType_Name(Py_TYPE(impl)));
        goto fail;
    }
    result = new_buffer(impl);
    impl = NULL;
    if (result != NULL)
        *pos = q;
    goto fail;
plain:
    PyErr_Clear();
fail:
    Py_XDECREF(name);
    Py_XDECREF(backend);
    Py_XDECREF(program);
    Py_XDECREF(descriptor);
    Py_XDECREF(impl);
    return result;
}

static PyObject *delegate_fail(PyObject *m) {
    Py_DECREF(m);
    return NULL;
}

/* An array's length, or a sequence's count read at *q (aligned first; *q moves past it) and
 * within its bound: 0 when it cannot be read here (the field's Python read then says why). */
static int element_count(RCtx *c, Op *op, Py_ssize_t *q, Py_ssize_t *n) {
    if (!op->is_sequence) {
        *n = op->array_length;
        return 1;
    }
    *q = align(*q, 4);
    if (*q > c->len - 4)
        return 0;
    *n = get_u32(c->data + *q);
    *q += 4;
    return !(op->bound && *n > op->bound);
}

static PyObject *program_read(Program *p, RCtx *c, Py_ssize_t *pos, int top) {
    PyObject *m = p->cls->tp_alloc(p->cls, 0);
    Py_ssize_t at = *pos;
    if (m == NULL)
        return NULL;
    for (int i = 0; i < p->nops; i++) {
        Op *op = &p->ops[i];
        PyObject *v = NULL;
        Py_ssize_t start = at;
        switch (op->code) {
        case OP_RUN: {
            if (run_end(op, at) > c->len) {
                PyObject *ctx = read_context(c, top), *ppos;
                if (ctx == NULL || (ppos = PyLong_FromSsize_t(at)) == NULL)
                    return delegate_fail(m);
                at = pos_result(PyObject_CallMethodObjArgs(op->step, G.s_read, ctx, m, ppos, NULL));
                Py_DECREF(ppos);
                if (at < 0)
                    return delegate_fail(m);
                continue;
            }
            for (int k = 0; k < op->nprims; k++) {
                Prim *prim = &op->prims[k];
                int w = WIDTH[prim->kind];
                at = align(at, w);
                if ((v = get_primitive(c->data + at, prim->kind)) == NULL)
                    return delegate_fail(m);
                set_slot(m, prim->off, v);
                at += w;
            }
            continue;
        }
        case OP_STRING:
            v = string_read(c, &at, op->string_bound);
            break;
        case OP_NESTED:
            if ((v = program_read(op->sub, c, &at, 0)) == NULL)
                return delegate_fail(m);
            break;
        case OP_NUMARRAY: {
            int w = WIDTH[op->kind];
            Py_ssize_t q = at, n;
            if (!element_count(c, op, &q, &n))
                break;
            if (n)
                q = align(q, w);
            if (q > c->len || n * w > c->len - q)
                break;
            PyObject *args[4] = {c->owner, op->dtype, PyLong_FromSsize_t(n), PyLong_FromSsize_t(q)};
            PyObject *wire = NULL;
            if (args[2] != NULL && args[3] != NULL)
                wire = PyObject_Vectorcall(G.frombuffer, args, 4, NULL);
            Py_XDECREF(args[2]);
            Py_XDECREF(args[3]);
            if (wire == NULL)
                return delegate_fail(m);
            v = PyObject_CallMethodOneArg(wire, G.s_astype, op->native);
            Py_DECREF(wire);
            if (v == NULL)
                return delegate_fail(m);
            at = q + n * w;
            break;
        }
        case OP_STRARRAY:
        case OP_MSGARRAY: {
            Py_ssize_t q = at, n;
            /* (each element takes a byte at least: a count past the bytes left is refused) */
            if (!element_count(c, op, &q, &n) || (op->is_sequence && n > c->len - q))
                break;
            PyObject *list = PyList_New(n);
            if (list == NULL)
                return delegate_fail(m);
            Py_ssize_t k;
            for (k = 0; k < n; k++) {
                PyObject *item;
                if (op->code == OP_STRARRAY) {
                    item = string_read(c, &q, op->string_bound);
                    if (item == NULL)
                        break;
                } else if ((item = program_read(op->sub, c, &q, 0)) == NULL) {
                    Py_DECREF(list);
                    return delegate_fail(m);
                }
                PyList_SET_ITEM(list, k, item);
            }
            if (k < n) {  /* a string that is not the plain case: the Python field reads it all */
                Py_DECREF(list);
                if (PyErr_Occurred())
                    return delegate_fail(m);
                break;
            }
            v = list;
            at = q;
            break;
        }
        case OP_BUFFER: {
            Py_ssize_t q = align(at, 4);
            if (q > c->len - 4)
                break;
            uint32_t n = get_u32(c->data + q);
            if (n != MARKER) {
                if (n <= (uint64_t)(c->len - q - 4)) {
                    if ((v = cpu_buffer(c, q + 4, n)) == NULL)
                        return delegate_fail(m);
                    at = q + 4 + n;
                }
            } else if (top && q <= c->len - 12) {
                uint32_t length = get_u32(c->data + q + 8);
                if (get_u32(c->data + q + 4) == MARKER2 && length &&
                    length <= (uint64_t)(c->len - q - 12)) {
                    v = descriptor_read(op, c, &at, q + 12, length);
                    if (v == NULL && PyErr_Occurred())
                        return delegate_fail(m);
                }
            }
            break;
        }
        }
        if (v == NULL) {
            if (PyErr_Occurred())
                return delegate_fail(m);
            at = start;
            if ((v = delegate_read(c, op->step, &at, top)) == NULL)
                return delegate_fail(m);
        }
        set_slot(m, op->off, v);
    }
    *pos = at;
    return m;
}

/* deserialize(program, data, backends, endpoint_info) -> message, or FALLBACK when the input
 * is not a plain bytes-like of CDR_LE (the Python path decodes it, or raises its error). */
static PyObject *deserialize(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 4 || !PyObject_TypeCheck(args[0], &ProgramType)) {
        PyErr_SetString(PyExc_TypeError, "deserialize(program, data, backends, endpoint_info)");
        return NULL;
    }
    PyObject *data = args[1];
    Py_buffer view;
    int has_view = 0;
    RCtx c = {0};
    c.owner = data;
    c.backends = args[2];
    c.endpoint_info = args[3];
    if (PyBytes_CheckExact(data)) {
        c.data = (const unsigned char *)PyBytes_AS_STRING(data);
        c.len = PyBytes_GET_SIZE(data);
    } else {
        if (PyObject_GetBuffer(data, &view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) {
            PyErr_Clear();
            Py_INCREF(G.fallback);
            return G.fallback;
        }
        has_view = 1;
        if (view.ndim > 1 || view.itemsize != 1 ||
            (view.format != NULL && strcmp(view.format, "B") != 0)) {
            PyBuffer_Release(&view);
            Py_INCREF(G.fallback);
            return G.fallback;
        }
        c.data = view.buf;
        c.len = view.len;
    }
    PyObject *m;
    if (c.len < ORIGIN || c.data[0] != 0 || c.data[1] != 1) {
        Py_INCREF(G.fallback);
        m = G.fallback;
    } else {
        Py_ssize_t pos = ORIGIN;
        m = program_read((Program *)args[0], &c, &pos, 1);
    }
    Py_XDECREF(c.ctx[0]);
    Py_XDECREF(c.ctx[1]);
    Py_XDECREF(c.view);
    if (has_view)
        PyBuffer_Release(&view);
    return m;
}

static PyMethodDef methods[] = {
    {"configure", (PyCFunction)(void (*)(void))configure, METH_VARARGS | METH_KEYWORDS,
     "Once, from rosidl_buffer.messages._cdr: the Python objects the codec calls."},
    {"serialize", (PyCFunction)(void (*)(void))serialize, METH_FASTCALL,
     "serialize(program, message, route, out) -> bytearray"},
    {"deserialize", (PyCFunction)(void (*)(void))deserialize, METH_FASTCALL,
     "deserialize(program, data, backends, endpoint_info) -> message or FALLBACK"},
    {NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "rosidl_buffer._cdr_native",
    "The per-message CDR codec in C (see rosidl_buffer/messages/_cdr.py).", -1, methods,
};

PyMODINIT_FUNC PyInit__cdr_native(void) {
    if (PyType_Ready(&ProgramType) < 0)
        return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m == NULL)
        return NULL;
#define INTERN(field, text) if ((G.field = PyUnicode_InternFromString(text)) == NULL) goto fail
    INTERN(s_size, "size");
    INTERN(s_write, "write");
    INTERN(s_read, "read");
    INTERN(s_check, "_check");
    INTERN(s_astype, "astype");
    INTERN(s_dtype, "dtype");
    INTERN(s_from, "from_descriptor_with_endpoint");
    INTERN(s_get, "get");
    INTERN(s_impl, "_impl");
    INTERN(s_cast, "cast");
    INTERN(s_B, "B");
#undef INTERN
    if ((G.fallback = PyObject_CallNoArgs((PyObject *)&PyBaseObject_Type)) == NULL)
        goto fail;
    Py_INCREF(G.fallback);
    if (PyModule_AddObject(m, "FALLBACK", G.fallback) < 0)
        goto fail;
    Py_INCREF(&ProgramType);
    if (PyModule_AddObject(m, "Program", (PyObject *)&ProgramType) < 0)
        goto fail;
    static const char *ops[] = {"OP_RUN", "OP_STRING", "OP_NESTED", "OP_NUMARRAY", "OP_STRARRAY",
                                "OP_MSGARRAY", "OP_BUFFER"};
    for (int i = 0; i < 7; i++)
        if (PyModule_AddIntConstant(m, ops[i], i) < 0)
            goto fail;
    static const char *kinds[] = {"bool", "int8", "uint8", "int16", "uint16", "int32", "uint32",
                                  "int64", "uint64", "float32", "float64"};
    PyObject *k = PyDict_New();
    if (k == NULL)
        goto fail;
    for (int i = 0; i < P_COUNT; i++) {
        PyObject *v = PyLong_FromLong(i);
        if (v == NULL || PyDict_SetItemString(k, kinds[i], v) < 0) {
            Py_XDECREF(v);
            Py_DECREF(k);
            goto fail;
        }
        Py_DECREF(v);
    }
    if (PyModule_AddObject(m, "KINDS", k) < 0) {
        Py_DECREF(k);
        goto fail;
    }
    return m;
fail:
    Py_DECREF(m);
    return NULL;
}
