/* warp_buffer._core: the publisher's side (see warp_buffer/lease.py for the model).
 *
 * - ArenaCore: the per-message state of this process's arena (warp_buffer.arena.Arena keeps the
 *   allocator, the peer table and the hand-off server): generations, the peer slots' epochs and
 *   delivery numbers, the retire probe (an OFD write-lock probe on a block's lock range).
 * - PeerSlot: one peer subscription's delivery slot: the numbers of the descriptors sent to it.
 * - Exports: the export state of a block (a base of the pool's blocks): its generation and the
 *   peers it was sent to, with their delivery numbers; try_reclaim ends the export once no peer
 *   can still read it.
 * - Lease: one owner's use of a block, the state machine whose transitions are its methods, each
 *   under the lease's one lock; Token: a reader's hold on a re-armable lease, counted by the
 *   lease (its end is one decrement in C: no weak reference, no finalizer).
 *
 * CUDA work (events, streams) stays in Python: the lease calls warp_buffer.lease's helpers for
 * it, with its lock held, as the Python lease did.
 */
#define PY_SSIZE_T_CLEAN
#define _GNU_SOURCE 1  /* (as pyconfig.h defines it) */
#include <Python.h>
#include <structmember.h>
#include <pythread.h>

#include <errno.h>
#include <fcntl.h>
#include <stdint.h>
#include <string.h>
#include <sys/mman.h>
#include <unistd.h>

#include "_core.h"

#define SEQ_BITS 40
#define SEQ_MASK ((1ULL << SEQ_BITS) - 1)
enum { FREE, WRITABLE, WRITING, WRITTEN, READ, PUBLISHED };

/* Python helpers of warp_buffer.lease, set by configure() */
static PyObject *WriteStateClass, *CompleteWrite, *OrderAfterWrite, *WriteHandleError;
/* An object attribute Python may set but not delete (the C reads it without a NULL check): the
 * getset's closure is the field's offset in the object. */
#define OBJECT_FIELD(type, field) ((void *)offsetof(type, field))

static PyObject *object_field_get(PyObject *self, void *offset) {
    PyObject *value = *(PyObject **)((char *)self + (Py_ssize_t)offset);
    return Py_NewRef(value != NULL ? value : Py_None);
}

static int object_field_set(PyObject *self, PyObject *value, void *offset) {
    if (value == NULL) {
        PyErr_SetString(PyExc_AttributeError, "this attribute cannot be deleted (set it to None)");
        return -1;
    }
    PyObject **field = (PyObject **)((char *)self + (Py_ssize_t)offset);
    Py_XSETREF(*field, Py_NewRef(value));
    return 0;
}

static PyObject *str_closed, *str_sealed, *str_stream, *str_published, *str_read, *str_core,
                *str_give_back, *str_close, *str_protect, *str_protected, *str_try_reclaim,
                *str_ensure_arena_range, *str_is_cpu, *str_capacity, *str_writable;

/* ============================================================================= peer slots */
typedef struct {
    PyObject_HEAD
    uint32_t index, epoch, pid;
    uint64_t issued;   /* the last number handed out */
    uint64_t window;   /* how many of the latest descriptors the peer can still import (0: all) */
} PeerSlot;

static PyMemberDef peer_members[] = {
    {"index", T_UINT, offsetof(PeerSlot, index), READONLY, "the slot's index in the arena"},
    {"epoch", T_UINT, offsetof(PeerSlot, epoch), READONLY, "the slot's use (changes per peer)"},
    {"pid", T_UINT, offsetof(PeerSlot, pid), READONLY, "the peer's process"},
    {"issued", T_ULONGLONG, offsetof(PeerSlot, issued), READONLY, "the last number sent"},
    {"window", T_ULONGLONG, offsetof(PeerSlot, window), 0,
     "descriptors the peer can still import (its queue and a few in hand; 0: no limit)"},
    {NULL}
};

static PyObject *peer_repr(PeerSlot *self) {
    return PyUnicode_FromFormat("PeerSlot(index=%u, epoch=%u, pid=%u, issued=%llu, window=%llu)",
                                self->index, self->epoch, self->pid,
                                (unsigned long long)self->issued,
                                (unsigned long long)self->window);
}

PyTypeObject PeerSlotType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "warp_buffer._core.PeerSlot",
    .tp_doc = "One peer subscription's delivery slot in this process's arena "
              "(ArenaCore.open_slot).",
    .tp_basicsize = sizeof(PeerSlot),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_members = peer_members,
    .tp_repr = (reprfunc)peer_repr,
};

/* ============================================================================= arena core */
typedef struct {
    PyObject_HEAD
    unsigned char *base;
    int fd;
    uint64_t data_offset, data_bytes;
    uint64_t generations;           /* the last generation number handed out */
    uint32_t epochs[ARENA_MAX_PEERS];
    PeerSlot *slots[ARENA_MAX_PEERS];
} ArenaCore;

static inline volatile uint64_t *core_gen(ArenaCore *c, uint64_t offset) {
    return (volatile uint64_t *)(c->base + ARENA_GENS_OFFSET) + (offset - c->data_offset)
           / ARENA_MIN_BLOCK;
}

static inline uint64_t core_ack(ArenaCore *c, uint32_t index) {
    return *(volatile uint64_t *)(c->base + ARENA_ACKS_OFFSET + (size_t)index
                                  * ARENA_SLOT_STRIDE);
}

/* ArenaCore(base, fd, data_offset, data_bytes): the arena's mapping and memfd (the Arena's). */
static int core_init(ArenaCore *self, PyObject *args, PyObject *kwds) {
    static char *kwlist[] = {"base", "fd", "data_offset", "data_bytes", NULL};
    unsigned long long base, data_offset, data_bytes;
    int fd;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "KiKK", kwlist, &base, &fd, &data_offset,
                                     &data_bytes))
        return -1;
    if (data_offset < ARENA_GENS_OFFSET + data_bytes / ARENA_MIN_BLOCK * 8) {
        PyErr_SetString(PyExc_ValueError, "the generations do not fit before the data");
        return -1;
    }
    self->base = (unsigned char *)(uintptr_t)base;
    self->fd = fd;
    self->data_offset = data_offset;
    self->data_bytes = data_bytes;
    return 0;
}

static void core_dealloc(ArenaCore *self) {
    for (int i = 0; i < ARENA_MAX_PEERS; i++)
        Py_CLEAR(self->slots[i]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int core_check_block(ArenaCore *c, uint64_t offset, uint64_t capacity) {
    if (offset < c->data_offset || offset - c->data_offset >= c->data_bytes
            || (offset - c->data_offset) % ARENA_MIN_BLOCK || capacity < ARENA_MIN_BLOCK
            || (capacity & (capacity - 1))) {
        PyErr_Format(PyExc_ValueError, "no block of %llu bytes at offset %llu",
                     (unsigned long long)capacity, (unsigned long long)offset);
        return -1;
    }
    return 0;
}

/* A generation never used before, whose low bits hold log2(capacity). */
static uint64_t core_new_generation(ArenaCore *c, uint64_t offset, uint64_t capacity) {
    uint64_t generation = ++c->generations << ARENA_GENERATION_ORDER_BITS
                          | (uint64_t)(63 - __builtin_clzll(capacity));
    *core_gen(c, offset) = generation;
    return generation;
}

static PyObject *core_new_generation_py(ArenaCore *self, PyObject *args) {
    unsigned long long offset, capacity;
    if (!PyArg_ParseTuple(args, "KK", &offset, &capacity) || core_check_block(self, offset,
                                                                               capacity))
        return NULL;
    return PyLong_FromUnsignedLongLong(core_new_generation(self, offset, capacity));
}

/* End the export of the block at offset if no reader holds it: 1 done, 0 held, -1 error. */
static int core_try_retire(ArenaCore *c, uint64_t offset) {
    if (lock_range(c->fd, F_WRLCK, offset, ARENA_LOCK_SPAN) != 0) {
        if (errno == EAGAIN || errno == EACCES)
            return 0;
        PyErr_SetFromErrno(PyExc_OSError);
        return -1;
    }
    *core_gen(c, offset) = 0;
    lock_range(c->fd, F_UNLCK, offset, ARENA_LOCK_SPAN);
    return 1;
}

static PyObject *core_try_retire_py(ArenaCore *self, PyObject *arg) {
    unsigned long long offset = PyLong_AsUnsignedLongLong(arg);
    if (offset == (unsigned long long)-1 && PyErr_Occurred())
        return NULL;
    if (core_check_block(self, offset, ARENA_MIN_BLOCK))
        return NULL;
    int done = core_try_retire(self, offset);
    return done < 0 ? NULL : PyBool_FromLong(done);
}

/* open_slot(index, pid, window) -> PeerSlot: the slot's next use (a new epoch, no
 * acknowledgement yet). */
static PyObject *core_open_slot(ArenaCore *self, PyObject *args) {
    unsigned int index, pid;
    unsigned long long window;
    if (!PyArg_ParseTuple(args, "IIK", &index, &pid, &window))
        return NULL;
    if (index >= ARENA_MAX_PEERS)
        return PyErr_Format(PyExc_ValueError, "peer slot %u", index);
    PeerSlot *slot = PyObject_New(PeerSlot, &PeerSlotType);
    if (slot == NULL)
        return NULL;
    self->epochs[index]++;
    *(volatile uint64_t *)(self->base + ARENA_ACKS_OFFSET + (size_t)index * ARENA_SLOT_STRIDE) = 0;
    slot->index = index;
    slot->epoch = self->epochs[index];
    slot->pid = pid;
    slot->issued = 0;
    slot->window = window;
    Py_XSETREF(self->slots[index], (PeerSlot *)Py_NewRef(slot));
    return (PyObject *)slot;
}

/* close_slot(index): the peer is gone; what was sent to it pins nothing any more. */
static PyObject *core_close_slot(ArenaCore *self, PyObject *arg) {
    long index = PyLong_AsLong(arg);
    if (index == -1 && PyErr_Occurred())
        return NULL;
    if (index < 0 || index >= ARENA_MAX_PEERS)
        return PyErr_Format(PyExc_ValueError, "peer slot %ld", index);
    self->epochs[index]++;
    Py_CLEAR(self->slots[index]);
    Py_RETURN_NONE;
}

static PyObject *core_ack_py(ArenaCore *self, PyObject *arg) {
    long index = PyLong_AsLong(arg);
    if (index == -1 && PyErr_Occurred())
        return NULL;
    if (index < 0 || index >= ARENA_MAX_PEERS)
        return PyErr_Format(PyExc_ValueError, "peer slot %ld", index);
    return PyLong_FromUnsignedLongLong(core_ack(self, (uint32_t)index));
}

static PyObject *core_generation_py(ArenaCore *self, PyObject *arg) {
    unsigned long long offset = PyLong_AsUnsignedLongLong(arg);
    if (offset == (unsigned long long)-1 && PyErr_Occurred())
        return NULL;
    if (core_check_block(self, offset, ARENA_MIN_BLOCK))
        return NULL;
    return PyLong_FromUnsignedLongLong(*core_gen(self, offset));
}

static PyMethodDef core_methods[] = {
    {"new_generation", (PyCFunction)core_new_generation_py, METH_VARARGS,
     "new_generation(offset, capacity) -> int: start an export of that block."},
    {"try_retire", (PyCFunction)core_try_retire_py, METH_O,
     "try_retire(offset) -> bool: end the block's export if no reader holds it."},
    {"open_slot", (PyCFunction)core_open_slot, METH_VARARGS,
     "open_slot(index, pid, window) -> PeerSlot"},
    {"close_slot", (PyCFunction)core_close_slot, METH_O, "close_slot(index)"},
    {"ack", (PyCFunction)core_ack_py, METH_O,
     "ack(index) -> int: the last delivery the slot's peer acknowledged."},
    {"generation", (PyCFunction)core_generation_py, METH_O,
     "generation(offset) -> int: the generation word of the block at offset."},
    {NULL}
};

PyTypeObject ArenaCoreType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "warp_buffer._core.ArenaCore",
    .tp_doc = "ArenaCore(base, fd, data_offset, data_bytes): this process's arena, per message.",
    .tp_basicsize = sizeof(ArenaCore),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)core_init,
    .tp_dealloc = (destructor)core_dealloc,
    .tp_methods = core_methods,
};

/* ============================================================================= exports */
typedef struct {
    uint32_t slot;
    uint64_t sequence;
} pending_entry;

typedef struct {
    PyObject_HEAD
    PyObject *dict;          /* subclasses' attributes (a pool block's capacity, device, ...) */
    PyObject *weakrefs;
    PyObject *arena;         /* warp_buffer.arena.Arena, or None */
    ArenaCore *core;         /* its core */
    PyObject *cuda_uses;
    uint64_t offset, generation;
    pending_entry *pending;
    Py_ssize_t npending, cap;
} Exports;

static int exports_traverse(Exports *self, visitproc visit, void *arg) {
    Py_VISIT(self->dict);
    Py_VISIT(self->arena);
    Py_VISIT(self->cuda_uses);
    return 0;
}

static int exports_clear(Exports *self) {
    Py_CLEAR(self->dict);
    Py_CLEAR(self->arena);
    Py_CLEAR(self->core);
    Py_CLEAR(self->cuda_uses);
    return 0;
}

static void exports_dealloc(Exports *self) {
    PyObject_GC_UnTrack(self);
    if (self->weakrefs != NULL)
        PyObject_ClearWeakRefs((PyObject *)self);
    exports_clear(self);
    PyMem_Free(self->pending);
    Py_TYPE(self)->tp_free((PyObject *)self);  /* (a heap subtype's dealloc drops the type) */
}

static PyObject *exports_new(PyTypeObject *type, PyObject *args, PyObject *kwds) {
    Exports *self = (Exports *)type->tp_alloc(type, 0);
    if (self != NULL) {
        self->arena = Py_NewRef(Py_None);
        self->cuda_uses = Py_NewRef(Py_None);
    }
    return (PyObject *)self;
}

static int exports_init(Exports *self, PyObject *args, PyObject *kwds) {
    return 0;  /* subclasses call it with nothing */
}

static PyObject *exports_get_arena(Exports *self, void *closure) {
    return Py_NewRef(self->arena);
}

static int exports_set_arena(Exports *self, PyObject *value, void *closure) {
    if (value == NULL)
        value = Py_None;
    ArenaCore *core = NULL;
    if (value != Py_None) {
        PyObject *c = PyObject_GetAttr(value, str_core);
        if (c == NULL)
            return -1;
        if (!PyObject_TypeCheck(c, &ArenaCoreType)) {
            Py_DECREF(c);
            PyErr_SetString(PyExc_TypeError, "a block's arena has an ArenaCore as .core");
            return -1;
        }
        core = (ArenaCore *)c;
    }
    Py_XSETREF(self->core, core);
    Py_XSETREF(self->arena, Py_NewRef(value));
    return 0;
}

static PyObject *exports_get_pending(Exports *self, void *closure) {
    PyObject *out = PyDict_New();
    for (Py_ssize_t i = 0; out != NULL && i < self->npending; i++) {
        PyObject *k = PyLong_FromUnsignedLong(self->pending[i].slot);
        PyObject *v = PyLong_FromUnsignedLongLong(self->pending[i].sequence);
        if (k == NULL || v == NULL || PyDict_SetItem(out, k, v) != 0)
            Py_CLEAR(out);
        Py_XDECREF(k);
        Py_XDECREF(v);
    }
    return out;
}

static int exports_note(Exports *self, uint32_t slot, uint64_t sequence) {
    for (Py_ssize_t i = 0; i < self->npending; i++) {
        if (self->pending[i].slot == slot) {
            self->pending[i].sequence = sequence;
            return 0;
        }
    }
    if (self->npending == self->cap) {
        Py_ssize_t cap = self->cap ? self->cap * 2 : 4;
        pending_entry *grown = PyMem_Realloc(self->pending, (size_t)cap * sizeof(pending_entry));
        if (grown == NULL) {
            PyErr_NoMemory();
            return -1;
        }
        self->pending = grown;
        self->cap = cap;
    }
    self->pending[self->npending++] = (pending_entry){slot, sequence};
    return 0;
}

static int exports_set_pending(Exports *self, PyObject *value, void *closure) {
    if (value == NULL || !PyDict_Check(value)) {
        PyErr_SetString(PyExc_TypeError, "pending is a dict {slot: sequence}");
        return -1;
    }
    self->npending = 0;
    PyObject *k, *v;
    Py_ssize_t pos = 0;
    while (PyDict_Next(value, &pos, &k, &v)) {
        unsigned long slot = PyLong_AsUnsignedLong(k);
        unsigned long long seq = PyLong_AsUnsignedLongLong(v);
        if (PyErr_Occurred() || exports_note(self, (uint32_t)slot, seq) != 0)
            return -1;
    }
    return 0;
}

/* Has every peer the block was sent to imported it (or a later descriptor), gone away, or been
 * sent more than its window since (its keep-last queue overwrote it)? */
static int exports_delivered(Exports *self) {
    ArenaCore *c = self->core;
    for (Py_ssize_t i = 0; i < self->npending; i++) {
        uint32_t index = self->pending[i].slot;
        uint64_t sequence = self->pending[i].sequence;
        if (index >= ARENA_MAX_PEERS || c->epochs[index] != sequence >> SEQ_BITS)
            continue;  /* the peer was forgotten */
        if (core_ack(c, index) < sequence) {
            PeerSlot *slot = c->slots[index];
            if (slot == NULL || slot->window == 0
                    || slot->issued - (sequence & SEQ_MASK) < slot->window)
                return 0;
        }
    }
    return 1;
}

/* 1: the block may be written again or freed (its export ended), 0: not yet, -1: error. */
static int exports_try_reclaim_c(Exports *self) {
    if (self->generation == 0)
        return 1;
    if (self->core == NULL)
        return 1;  /* never in an arena: nobody else can read it */
    if (self->npending && !exports_delivered(self))
        return 0;  /* a descriptor is still on its way to a live peer */
    if (core_check_block(self->core, self->offset, ARENA_MIN_BLOCK))
        return -1;  /* (offset is settable from Python: never index the table with a bad one) */
    int done = core_try_retire(self->core, self->offset);
    if (done <= 0)
        return done;  /* a reader holds it, or an error */
    self->generation = 0;
    self->npending = 0;
    return 1;
}

static PyObject *exports_try_reclaim(Exports *self, PyObject *unused) {
    int done = exports_try_reclaim_c(self);
    return done < 0 ? NULL : PyBool_FromLong(done);
}

static PyObject *exports_ensure_arena_range(Exports *self, PyObject *unused) {
    Py_RETURN_NONE;  /* host blocks have one from the start; CUDA blocks override it */
}

static PyMethodDef exports_methods[] = {
    {"try_reclaim", (PyCFunction)exports_try_reclaim, METH_NOARGS,
     "May the block be written again or freed now? Ends its export if so."},
    {"ensure_arena_range", (PyCFunction)exports_ensure_arena_range, METH_NOARGS,
     "Give the block its arena range (host blocks have one from the start)."},
    {NULL}
};

static PyMemberDef exports_members[] = {
    {"offset", T_ULONGLONG, offsetof(Exports, offset), 0, "the block's lock range in the arena"},
    {"generation", T_ULONGLONG, offsetof(Exports, generation), 0,
     "the generation of the current export (0: none since the block was free)"},
    {"__dictoffset__", T_PYSSIZET, offsetof(Exports, dict), READONLY},
    {"__weaklistoffset__", T_PYSSIZET, offsetof(Exports, weakrefs), READONLY},
    {NULL}
};

static PyGetSetDef exports_getset[] = {
    {"arena", (getter)exports_get_arena, (setter)exports_set_arena,
     "the arena of the block's lock range (None: none yet)", NULL},
    {"pending", (getter)exports_get_pending, (setter)exports_set_pending,
     "peer slot -> delivery sequence of the last descriptor sent with the block (a copy)", NULL},
    {"cuda_uses", object_field_get, object_field_set,
     "last-use events of local readers (CUDA blocks)", OBJECT_FIELD(Exports, cuda_uses)},
    {"__dict__", PyObject_GenericGetDict, PyObject_GenericSetDict, NULL, NULL},
    {NULL}
};

PyTypeObject ExportsType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "warp_buffer._core.Exports",
    .tp_doc = "The export state of a block (a base of the pool's blocks).",
    .tp_basicsize = sizeof(Exports),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_BASETYPE | Py_TPFLAGS_HAVE_GC,
    .tp_new = exports_new,
    .tp_init = (initproc)exports_init,
    .tp_dealloc = (destructor)exports_dealloc,
    .tp_traverse = (traverseproc)exports_traverse,
    .tp_clear = (inquiry)exports_clear,
    .tp_methods = exports_methods,
    .tp_members = exports_members,
    .tp_getset = exports_getset,
    .tp_dictoffset = offsetof(Exports, dict),
    .tp_weaklistoffset = offsetof(Exports, weakrefs),
};

/* ============================================================================= fences */
/* The pages a loan protects (warp_buffer.loan): read-only in this process between publish and
 * the next loan, so a write through a stale view faults instead of changing what readers see. */
typedef struct {
    PyObject_HEAD
    unsigned char *addr;
    size_t nbytes;
    int window;      /* a mapping of our own (unmapped at close), else the block's own pages */
    int protected;
} Fence;

PyTypeObject FenceType;

static int fence_protect_c(Fence *self, int writable) {
    if (self->addr == NULL)
        return 0;
    if (mprotect(self->addr, self->nbytes, writable ? PROT_READ | PROT_WRITE : PROT_READ) != 0) {
        PyErr_Format(PyExc_OSError, "mprotect of a loaned block failed: %s", strerror(errno));
        return -1;
    }
    self->protected = !writable;
    return 0;
}

/* Fence(addr, nbytes, window) */
static int fence_init(Fence *self, PyObject *args, PyObject *kwds) {
    static char *kwlist[] = {"addr", "nbytes", "window", NULL};
    unsigned long long addr, nbytes;
    int window;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "KKp", kwlist, &addr, &nbytes, &window))
        return -1;
    self->addr = (unsigned char *)(uintptr_t)addr;
    self->nbytes = (size_t)nbytes;
    self->window = window;
    self->protected = 0;
    return 0;
}

/* Writable again whatever the last loan left: a window is unmapped, pages protected in place
 * are made writable. Idempotent. */
static void fence_close_c(Fence *self) {
    if (self->addr == NULL)
        return;
    if (self->window)
        munmap(self->addr, self->nbytes);
    else if (self->protected)
        mprotect(self->addr, self->nbytes, PROT_READ | PROT_WRITE);
    self->addr = NULL;
    self->protected = 0;
}

static void fence_dealloc(Fence *self) {
    fence_close_c(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject *fence_protect(Fence *self, PyObject *args, PyObject *kwds) {
    static char *kwlist[] = {"writable", NULL};
    int writable = 0;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "|p", kwlist, &writable))
        return NULL;
    if (fence_protect_c(self, writable) != 0)
        return NULL;
    Py_RETURN_NONE;
}

static PyObject *fence_close(Fence *self, PyObject *unused) {
    fence_close_c(self);
    Py_RETURN_NONE;
}

static PyMethodDef fence_methods[] = {
    {"protect", (PyCFunction)(void (*)(void))fence_protect, METH_VARARGS | METH_KEYWORDS,
     "protect(writable=False): read-only in this process (writable=True: writable again)."},
    {"close", (PyCFunction)fence_close, METH_NOARGS,
     "Writable again, or the window unmapped (idempotent)."},
    {NULL}
};

static PyMemberDef fence_members[] = {
    {"protected", T_BOOL, offsetof(Fence, protected), READONLY, "read-only now"},
    {"window", T_BOOL, offsetof(Fence, window), READONLY, "a mapping of the fence's own"},
    {"nbytes", T_ULONGLONG, offsetof(Fence, nbytes), READONLY, "bytes protected"},
    {NULL}
};

static PyObject *fence_get_addr(Fence *self, void *closure) {
    return PyLong_FromVoidPtr(self->addr);
}

static PyGetSetDef fence_getset[] = {
    {"addr", (getter)fence_get_addr, NULL, "the first page (0 once closed)", NULL},
    {NULL}
};

PyTypeObject FenceType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "warp_buffer._core.Fence",
    .tp_doc = "Fence(addr, nbytes, window): the pages a loan protects between publish and its "
              "next loan.",
    .tp_basicsize = sizeof(Fence),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)fence_init,
    .tp_dealloc = (destructor)fence_dealloc,
    .tp_methods = fence_methods,
    .tp_members = fence_members,
    .tp_getset = fence_getset,
};

/* ============================================================================= leases */
typedef struct {
    PyObject_HEAD
    PyObject *pool, *block, *device, *writer, *event, *fence, *write_stream;
    PyObject *weakrefs;
    int state, on_cpu, rearmable;
    Py_ssize_t readers;      /* tokens alive */
    PyThread_type_lock lock;
} Lease;

typedef struct {
    PyObject_HEAD
    Lease *lease;
} Token;

PyTypeObject LeaseType, TokenType;

/* The lease's lock: taken without the GIL when it is contended (a CUDA transition of another
 * thread calls into Python while it holds it). */
static void lease_lock(Lease *self) {
    if (!PyThread_acquire_lock(self->lock, NOWAIT_LOCK)) {
        Py_BEGIN_ALLOW_THREADS
        PyThread_acquire_lock(self->lock, WAIT_LOCK);
        Py_END_ALLOW_THREADS
    }
}

static void lease_unlock(Lease *self) {
    PyThread_release_lock(self->lock);
}

static PyObject *lease_new(PyTypeObject *type, PyObject *args, PyObject *kwds) {
    Lease *self = (Lease *)type->tp_alloc(type, 0);
    if (self == NULL)
        return NULL;
    self->lock = PyThread_allocate_lock();
    if (self->lock == NULL) {
        Py_DECREF(self);
        return PyErr_NoMemory();
    }
    PyObject **fields[] = {&self->pool, &self->block, &self->device, &self->writer, &self->event,
                           &self->fence, &self->write_stream};
    for (size_t i = 0; i < sizeof fields / sizeof *fields; i++)
        *fields[i] = Py_NewRef(Py_None);
    return (PyObject *)self;
}

/* Lease(pool, block, device, rearmable=False) */
static int lease_init(Lease *self, PyObject *args, PyObject *kwds) {
    static char *kwlist[] = {"pool", "block", "device", "rearmable", NULL};
    PyObject *pool, *block, *device;
    int rearmable = 0;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "OOO|p", kwlist, &pool, &block, &device,
                                     &rearmable))
        return -1;
    PyObject *is_cpu = PyObject_GetAttr(device, str_is_cpu);
    if (is_cpu == NULL)
        return -1;
    int on_cpu = PyObject_IsTrue(is_cpu);
    Py_DECREF(is_cpu);
    if (on_cpu < 0)
        return -1;
    Py_XSETREF(self->pool, Py_NewRef(pool));
    Py_XSETREF(self->block, Py_NewRef(block));
    Py_XSETREF(self->device, Py_NewRef(device));
    self->on_cpu = on_cpu;
    self->state = WRITABLE;
    self->rearmable = rearmable;
    return 0;
}

static int lease_traverse(Lease *self, visitproc visit, void *arg) {
    Py_VISIT(self->pool);
    Py_VISIT(self->block);
    Py_VISIT(self->device);
    Py_VISIT(self->writer);
    Py_VISIT(self->event);
    Py_VISIT(self->fence);
    Py_VISIT(self->write_stream);
    return 0;
}

static int lease_clear(Lease *self) {
    Py_CLEAR(self->pool);
    Py_CLEAR(self->block);
    Py_CLEAR(self->device);
    Py_CLEAR(self->writer);
    Py_CLEAR(self->event);
    Py_CLEAR(self->fence);
    Py_CLEAR(self->write_stream);
    return 0;
}

/* Owner, arrays and tokens are all gone: FREE. The fence comes down, then the block goes back
 * to its pool (a lock-free queue). No lock: this may run inside any critical section. */
static void lease_finalize(Lease *self) {
    PyObject *type, *value, *tb;
    PyErr_Fetch(&type, &value, &tb);
    self->state = FREE;
    PyObject *fence = self->fence;
    if (fence != NULL && Py_IS_TYPE(fence, &FenceType)) {
        fence_close_c((Fence *)fence);
    } else if (fence != NULL && fence != Py_None) {
        self->fence = Py_NewRef(Py_None);
        PyObject *r = PyObject_CallMethodNoArgs(fence, str_close);
        if (r == NULL)
            PyErr_WriteUnraisable(fence);
        Py_XDECREF(r);
        Py_DECREF(fence);
    }
    if (self->pool != NULL && self->pool != Py_None && self->block != NULL) {
        PyObject *r = PyObject_CallMethodOneArg(self->pool, str_give_back, self->block);
        if (r == NULL)
            PyErr_WriteUnraisable(self->pool);
        Py_XDECREF(r);
    }
    PyErr_Restore(type, value, tb);
}

static void lease_dealloc(Lease *self) {
    if (PyObject_CallFinalizerFromDealloc((PyObject *)self) < 0)
        return;  /* resurrected */
    PyObject_GC_UnTrack(self);
    if (self->weakrefs != NULL)
        PyObject_ClearWeakRefs((PyObject *)self);
    lease_clear(self);
    if (self->lock != NULL)
        PyThread_free_lock(self->lock);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject *lease_repr(Lease *self) {
    static const char *names[] = {"free", "writable", "writing", "written", "read", "published"};
    return PyUnicode_FromFormat("Lease(%s, block=%R)", names[self->state], self->block);
}

/* As the deleter of an array over the memory (ptr, size): the array only keeps the lease. */
static PyObject *lease_call(PyObject *self, PyObject *args, PyObject *kwds) {
    Py_RETURN_NONE;
}

/* Record the write's completion (CUDA; cpu writes are synchronous). With the lock held. */
static int lease_complete(Lease *self, PyObject *stream) {
    if (self->on_cpu)
        return 0;
    PyObject *r = PyObject_CallFunctionObjArgs(CompleteWrite, (PyObject *)self, stream, NULL);
    Py_XDECREF(r);
    return r == NULL ? -1 : 0;
}

static int attr_true(PyObject *obj, PyObject *name) {
    PyObject *v = PyObject_GetAttr(obj, name);
    if (v == NULL)
        return -1;
    int t = PyObject_IsTrue(v);
    Py_DECREF(v);
    return t;
}

/* End an open write with ``why`` ("published" / "read") and record its completion. */
static int lease_end_writer(Lease *self, PyObject *why) {
    PyObject *writer = self->writer;
    if (writer == Py_None)
        return 0;
    self->writer = Py_NewRef(Py_None);
    int closed = attr_true(writer, str_closed);
    int rc = closed;
    if (closed == 0) {
        rc = PyObject_SetAttr(writer, str_sealed, why);
        if (rc == 0) {
            PyObject *stream = PyObject_GetAttr(writer, str_stream);
            rc = stream == NULL ? -1 : lease_complete(self, stream);
            Py_XDECREF(stream);
        }
    }
    Py_DECREF(writer);
    return rc < 0 ? -1 : 0;
}

static PyObject *lease_open_write(Lease *self, PyObject *stream) {
    lease_lock(self);
    PyObject *result = NULL;
    if (self->state != WRITABLE) {
        PyErr_SetString(WriteHandleError ? WriteHandleError : PyExc_RuntimeError,
                        self->state == PUBLISHED
                            ? "this buffer was published; it can no longer be written"
                            : self->state == READ
                                ? "this buffer was read; it can no longer be written"
                                : "a buffer accepts one write handle, ever");
    } else {
        result = PyObject_CallOneArg(WriteStateClass, stream);
        if (result != NULL) {
            self->state = WRITING;
            Py_XSETREF(self->writer, Py_NewRef(result));
        }
    }
    lease_unlock(self);
    return result;
}

static PyObject *lease_close_write(Lease *self, PyObject *writer) {
    lease_lock(self);
    int rc = 0;
    if (self->writer == writer) {
        Py_XSETREF(self->writer, Py_NewRef(Py_None));
        if (self->state == WRITING)
            self->state = WRITTEN;
        int closed = attr_true(writer, str_closed);
        if (closed < 0) {
            rc = -1;
        } else if (!closed) {
            PyObject *stream = PyObject_GetAttr(writer, str_stream);
            rc = stream == NULL ? -1 : lease_complete(self, stream);
            Py_XDECREF(stream);
        }
    }
    lease_unlock(self);
    if (rc < 0)
        return NULL;
    Py_RETURN_NONE;
}

/* The handle ``writer`` was collected (a finalizer): its write ends without the lock. */
static PyObject *lease_end_write_quietly(Lease *self, PyObject *writer) {
    if (self->writer != writer)
        Py_RETURN_NONE;
    int closed = attr_true(writer, str_closed);
    if (closed < 0)
        return NULL;
    PyObject *sealed = PyObject_GetAttr(writer, str_sealed);
    if (sealed == NULL)
        return NULL;
    int open = !closed && sealed == Py_None;
    Py_DECREF(sealed);
    if (!open)
        Py_RETURN_NONE;
    if (PyObject_SetAttr(writer, str_closed, Py_True) != 0)
        return NULL;
    PyObject *stream = PyObject_GetAttr(writer, str_stream);
    int rc = stream == NULL ? -1 : lease_complete(self, stream);
    Py_XDECREF(stream);
    if (rc < 0)
        return NULL;
    Py_RETURN_NONE;
}

/* -> PUBLISHED, once per publish (idempotent). */
static PyObject *lease_seal(Lease *self, PyObject *unused) {
    if (self->state == PUBLISHED && self->writer == Py_None)
        Py_RETURN_NONE;  /* sealed already: only reclaim (the owner's) changes it */
    lease_lock(self);
    int rc = 0;
    if (self->writer != Py_None)
        rc = lease_end_writer(self, str_published);
    else if (self->state == WRITABLE && !self->on_cpu)
        rc = lease_complete(self, self->write_stream);  /* written without a handle */
    self->state = PUBLISHED;
    lease_unlock(self);
    if (rc < 0)
        return NULL;
    Py_RETURN_NONE;
}

/* -> READ (a reader took it; a published lease stays PUBLISHED). */
static PyObject *lease_mark_read(Lease *self, PyObject *unused) {
    if (self->state >= READ && self->writer == Py_None)
        Py_RETURN_NONE;
    lease_lock(self);
    int rc = lease_end_writer(self, str_read);
    if (self->state < READ)
        self->state = READ;
    lease_unlock(self);
    if (rc < 0)
        return NULL;
    Py_RETURN_NONE;
}

static PyObject *lease_complete_write(Lease *self, PyObject *stream) {
    lease_lock(self);
    int rc = lease_complete(self, stream);
    lease_unlock(self);
    if (rc < 0)
        return NULL;
    Py_RETURN_NONE;
}

static PyObject *lease_order_after_write(Lease *self, PyObject *stream) {
    if (self->on_cpu)
        Py_RETURN_NONE;
    lease_lock(self);
    PyObject *r = PyObject_CallFunctionObjArgs(OrderAfterWrite, (PyObject *)self, stream, NULL);
    lease_unlock(self);
    return r;
}

/* A reader's token: a Token for a re-armable lease, the lease itself otherwise. */
static PyObject *lease_hold(Lease *self, PyObject *unused) {
    if (!self->rearmable)
        return Py_NewRef((PyObject *)self);
    Token *token = PyObject_New(Token, &TokenType);
    if (token == NULL)
        return NULL;
    token->lease = (Lease *)Py_NewRef((PyObject *)self);
    self->readers++;
    return (PyObject *)token;
}

/* Published to a peer (a PeerSlot; None: no delivery accounting): the generation of the
 * block's current export (a new one when it is the first since the block was free), the peer's
 * slot and the delivery sequence the block now waits for. 0 or -1 (an error set). */
static int lease_export_c(Lease *self, PyObject *peer, uint64_t *generation_out,
                          uint32_t *slot_out, uint64_t *sequence_out, Exports **block_out) {
    if (peer != Py_None && !PyObject_TypeCheck(peer, &PeerSlotType)) {
        PyErr_SetString(PyExc_TypeError, "export(peer): a PeerSlot or None");
        return -1;
    }
    if (!PyObject_TypeCheck(self->block, &ExportsType)) {
        PyErr_SetString(PyExc_TypeError, "this lease's block cannot be exported");
        return -1;
    }
    /* Held: the Python calls below (ensure_arena_range, capacity) may replace lease.block. */
    Exports *block = (Exports *)Py_NewRef(self->block);
    lease_lock(self);
    int rc = -1;
    uint64_t generation = block->generation;
    if (generation == 0) {  /* the first export since the block was free: a new generation */
        if (block->core == NULL) {
            PyObject *r = PyObject_CallMethodNoArgs((PyObject *)block, str_ensure_arena_range);
            if (r == NULL)
                goto done;
            Py_DECREF(r);
            if (block->core == NULL) {
                PyErr_SetString(PyExc_OSError, "the block has no arena range");
                goto done;
            }
        }
        PyObject *cap = PyObject_GetAttr((PyObject *)block, str_capacity);
        if (cap == NULL)
            goto done;
        unsigned long long capacity = PyLong_AsUnsignedLongLong(cap);
        Py_DECREF(cap);
        if (PyErr_Occurred())
            goto done;
        if (capacity < ARENA_MIN_BLOCK || (capacity & (capacity - 1))) {
            PyErr_Format(PyExc_ValueError, "a block of %llu bytes", capacity);
            goto done;
        }
        if (core_check_block(block->core, block->offset, ARENA_MIN_BLOCK))
            goto done;  /* (offset is settable from Python: never index the table with a bad one) */
        /* (a CUDA block's lock range is one MIN_BLOCK; its generation names its capacity) */
        generation = block->generation = core_new_generation(block->core, block->offset,
                                                             capacity);
    }
    *generation_out = generation;
    if (peer == Py_None) {
        *slot_out = ARENA_NO_PEER;
        *sequence_out = 0;
        rc = 0;
        goto done;
    }
    PeerSlot *slot = (PeerSlot *)peer;
    uint64_t sequence = (uint64_t)slot->epoch << SEQ_BITS | ++slot->issued;
    if (exports_note(block, slot->index, sequence) != 0)
        goto done;
    *slot_out = slot->index;
    *sequence_out = sequence;
    rc = 0;
done:
    lease_unlock(self);
    if (rc == 0 && block_out != NULL)
        *block_out = block;  /* the caller's reference now */
    else
        Py_DECREF(block);
    return rc;
}

/* export(peer) -> (generation, slot, sequence) */
static PyObject *lease_export(Lease *self, PyObject *peer) {
    uint64_t generation, sequence;
    uint32_t slot;
    if (lease_export_c(self, peer, &generation, &slot, &sequence, NULL) != 0)
        return NULL;
    return Py_BuildValue("(KIK)", (unsigned long long)generation, slot,
                         (unsigned long long)sequence);
}

/* -- descriptors --------------------------------------------------------------------------- */
static PyTypeObject *DescriptorType;          /* the generated message class */
static Py_ssize_t descriptor_offsets[DESC_FIELDS];  /* where each field's slot is in it */
static PyObject *empty_tuple;

/* set_descriptor_type(cls, fields): the message class descriptors are made of, whose slots are
 * ``fields`` in warp_buffer.descriptor.FIELDS order. */
PyObject *set_descriptor_type(PyObject *module, PyObject *args) {
    PyObject *cls, *fields;
    if (!PyArg_ParseTuple(args, "O!O", &PyType_Type, &cls, &fields))
        return NULL;
    PyObject *seq = PySequence_Fast(fields, "fields");
    if (seq == NULL)
        return NULL;
    if (PySequence_Fast_GET_SIZE(seq) != DESC_FIELDS) {
        Py_DECREF(seq);
        return PyErr_Format(PyExc_ValueError, "a descriptor has %d fields", DESC_FIELDS);
    }
    Py_ssize_t offsets[DESC_FIELDS];
    for (int i = 0; i < DESC_FIELDS; i++) {
        PyObject *member = PyObject_GetAttr(cls, PySequence_Fast_GET_ITEM(seq, i));
        if (member == NULL) {
            Py_DECREF(seq);
            return NULL;
        }
        int ok = Py_IS_TYPE(member, &PyMemberDescr_Type)
                 && ((PyMemberDescrObject *)member)->d_member->type == T_OBJECT_EX;
        if (ok)
            offsets[i] = ((PyMemberDescrObject *)member)->d_member->offset;
        Py_DECREF(member);
        if (!ok) {
            Py_DECREF(seq);
            return PyErr_Format(PyExc_TypeError, "descriptor field %d is not a slot", i);
        }
    }
    Py_DECREF(seq);
    memcpy(descriptor_offsets, offsets, sizeof offsets);
    Py_XSETREF(DescriptorType, (PyTypeObject *)Py_NewRef(cls));
    if (empty_tuple == NULL && (empty_tuple = PyTuple_New(0)) == NULL)
        return NULL;
    Py_RETURN_NONE;
}

/* A descriptor message of the 27 values (its slots written as their setters would). */
static PyObject *make_descriptor(const uint64_t *v) {
    if (DescriptorType == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "no descriptor type (set_descriptor_type)");
        return NULL;
    }
    PyObject *obj = DescriptorType->tp_new(DescriptorType, empty_tuple, NULL);
    if (obj == NULL)
        return NULL;
    for (int i = 0; i < DESC_FIELDS; i++) {
        PyObject *value = PyLong_FromUnsignedLongLong(v[i]);
        if (value == NULL) {
            Py_DECREF(obj);
            return NULL;
        }
        PyObject **slot = (PyObject **)((char *)obj + descriptor_offsets[i]);
        Py_XSETREF(*slot, value);
    }
    return obj;
}

/* make(values) -> descriptor: its 27 field values, as given (no check: the values come from
 * this process's own bookkeeping or from the fixed layout; an import checks what it reads). */
PyObject *make_descriptor_py(PyObject *module, PyObject *values) {
    if (DescriptorType == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "no descriptor type (set_descriptor_type)");
        return NULL;
    }
    PyObject *seq = PySequence_Fast(values, "descriptor values must be a sequence");
    if (seq == NULL)
        return NULL;
    if (PySequence_Fast_GET_SIZE(seq) != DESC_FIELDS) {
        Py_DECREF(seq);
        return descriptor_error("a descriptor has %d fields", DESC_FIELDS);
    }
    PyObject *obj = DescriptorType->tp_new(DescriptorType, empty_tuple, NULL);
    if (obj != NULL) {
        for (int i = 0; i < DESC_FIELDS; i++) {
            PyObject **slot = (PyObject **)((char *)obj + descriptor_offsets[i]);
            Py_XSETREF(*slot, Py_NewRef(PySequence_Fast_GET_ITEM(seq, i)));
        }
    }
    Py_DECREF(seq);
    return obj;
}

/* describe(lease, peer, kind, size, owner_pid, session, device_word=0, handles=None) ->
 * descriptor: the lease's block exported to ``peer`` (Lease.export) and described, in one call.
 * ``handles``: the 16 CUDA handle words (None: zeros). */
PyObject *describe(PyObject *module, PyObject *args) {
    PyObject *lease, *peer, *handles = Py_None;
    unsigned int kind, pid;
    unsigned long long size, session, device_word = 0;
    if (!PyArg_ParseTuple(args, "O!OIKIK|KO", &LeaseType, &lease, &peer, &kind, &size, &pid,
                          &session, &device_word, &handles))
        return NULL;
    uint64_t v[DESC_FIELDS] = {0};
    if (handles != Py_None) {
        PyObject *seq = PySequence_Fast(handles, "handles must be a sequence");
        if (seq == NULL)
            return NULL;
        if (PySequence_Fast_GET_SIZE(seq) != 2 * DESC_HANDLE_WORDS) {
            Py_DECREF(seq);
            return descriptor_error("%d handle words", 2 * DESC_HANDLE_WORDS);
        }
        for (int i = 0; i < 2 * DESC_HANDLE_WORDS; i++) {
            if (field_value(PySequence_Fast_GET_ITEM(seq, i), 11 + i, &v[11 + i]) != 0) {
                Py_DECREF(seq);
                return NULL;
            }
        }
        Py_DECREF(seq);
    }
    uint64_t generation, sequence;
    uint32_t slot;
    Exports *block;  /* the block exported, held while Python code runs (capacity) */
    if (lease_export_c((Lease *)lease, peer, &generation, &slot, &sequence, &block) != 0)
        return NULL;
    PyObject *cap = PyObject_GetAttr((PyObject *)block, str_capacity);
    unsigned long long capacity = cap == NULL ? 0 : PyLong_AsUnsignedLongLong(cap);
    Py_XDECREF(cap);
    uint64_t offset = block->offset;
    Py_DECREF(block);
    if (PyErr_Occurred())
        return NULL;
    v[F_VERSION] = DESC_VERSION;
    v[F_KIND] = kind;
    v[F_SLOT] = slot;
    v[F_PID] = pid;
    v[F_SESSION] = session;
    v[F_OFFSET] = offset;
    v[F_CAPACITY] = capacity;
    v[F_SIZE] = size;
    v[F_GENERATION] = generation;
    v[F_SEQUENCE] = sequence;
    v[F_DEVICE] = device_word;
    return make_descriptor(v);
}

/* Every route of the publish sent the message: the fence goes up. */
static PyObject *lease_end_publish(Lease *self, PyObject *unused) {
    PyObject *fence = self->fence;
    if (fence == Py_None)
        Py_RETURN_NONE;
    if (Py_IS_TYPE(fence, &FenceType)) {
        if (((Fence *)fence)->protected)
            Py_RETURN_NONE;
        lease_lock(self);
        int rc = 0;
        if (self->state == PUBLISHED && self->fence == fence && !((Fence *)fence)->protected)
            rc = fence_protect_c((Fence *)fence, 0);
        lease_unlock(self);
        if (rc < 0)
            return NULL;
        Py_RETURN_NONE;
    }
    int protected = attr_true(fence, str_protected);
    if (protected != 0)
        return protected < 0 ? NULL : Py_NewRef(Py_None);
    lease_lock(self);
    int rc = 0;
    if (self->state == PUBLISHED && self->fence != Py_None) {
        protected = attr_true(self->fence, str_protected);
        if (protected < 0) {
            rc = -1;
        } else if (!protected) {
            PyObject *r = PyObject_CallMethodNoArgs(self->fence, str_protect);
            rc = r == NULL ? -1 : 0;
            Py_XDECREF(r);
        }
    }
    lease_unlock(self);
    if (rc < 0)
        return NULL;
    Py_RETURN_NONE;
}

/* try_reclaim of a block: ours in C unless its type overrides it (CUDA blocks check their last
 * uses first): 1, 0, or -1 on error. */
static int block_try_reclaim(PyObject *block) {
    if (PyObject_TypeCheck(block, &ExportsType)) {
        PyObject *method = _PyType_Lookup(Py_TYPE(block), str_try_reclaim);
        if (method != NULL && Py_IS_TYPE(method, &PyMethodDescr_Type)
                && ((PyMethodDescrObject *)method)->d_method->ml_meth
                       == (PyCFunction)exports_try_reclaim)
            return exports_try_reclaim_c((Exports *)block);
    }
    PyObject *r = PyObject_CallMethodNoArgs(block, str_try_reclaim);
    int done = r == NULL ? -1 : PyObject_IsTrue(r);
    Py_XDECREF(r);
    return done;
}

/* PUBLISHED -> WRITABLE when nobody can read the bytes any more; False while held. */
static PyObject *lease_reclaim(Lease *self, PyObject *unused) {
    lease_lock(self);
    PyObject *result = NULL;
    if (self->readers > 0) {
        result = Py_NewRef(Py_False);
        goto done;
    }
    if (self->block != Py_None) {
        int done = block_try_reclaim(self->block);
        if (done <= 0) {
            result = done < 0 ? NULL : Py_NewRef(Py_False);
            goto done;
        }
    }
    if (Py_IS_TYPE(self->fence, &FenceType)) {
        if (((Fence *)self->fence)->protected && fence_protect_c((Fence *)self->fence, 1) != 0)
            goto done;
    } else if (self->fence != Py_None) {
        int protected = attr_true(self->fence, str_protected);
        if (protected < 0)
            goto done;
        if (protected) {
            PyObject *r = PyObject_CallMethodObjArgs(self->fence, str_protect, Py_True, NULL);
            if (r == NULL)
                goto done;
            Py_DECREF(r);
        }
    }
    self->state = WRITABLE;
    Py_XSETREF(self->writer, Py_NewRef(Py_None));
    Py_XSETREF(self->event, Py_NewRef(Py_None));
    Py_XSETREF(self->write_stream, Py_NewRef(Py_None));
    result = Py_NewRef(Py_True);
done:
    lease_unlock(self);
    return result;
}

static PyObject *lease_adopt(Lease *self, PyObject *args) {
    PyObject *block, *pool;
    if (!PyArg_ParseTuple(args, "OO", &block, &pool))
        return NULL;
    lease_lock(self);
    Py_XSETREF(self->block, Py_NewRef(block));
    Py_XSETREF(self->pool, Py_NewRef(pool));
    lease_unlock(self);
    Py_RETURN_NONE;
}

static PyObject *lease_get_readers(Lease *self, void *closure) {
    return PyLong_FromSsize_t(self->readers);
}

static PyMethodDef lease_methods[] = {
    {"open_write", (PyCFunction)lease_open_write, METH_O,
     "WRITABLE -> WRITING: the buffer's one write handle (a WriteState)."},
    {"close_write", (PyCFunction)lease_close_write, METH_O,
     "WRITING -> WRITTEN: the handle was released; its completion is recorded."},
    {"end_write_quietly", (PyCFunction)lease_end_write_quietly, METH_O,
     "The handle was collected: its write ends without the lock."},
    {"seal", (PyCFunction)lease_seal, METH_NOARGS, "-> PUBLISHED, once per publish."},
    {"mark_read", (PyCFunction)lease_mark_read, METH_NOARGS, "-> READ (a reader took it)."},
    {"complete_write", (PyCFunction)lease_complete_write, METH_O,
     "Record that every write enqueued on the stream completed (CUDA)."},
    {"order_after_write", (PyCFunction)lease_order_after_write, METH_O,
     "Order work on a CUDA stream after the write."},
    {"hold", (PyCFunction)lease_hold, METH_NOARGS,
     "A reader's token (a Token for a re-armable lease, the lease itself otherwise)."},
    {"export", (PyCFunction)lease_export, METH_O,
     "export(peer) -> (generation, slot, sequence): published to a peer."},
    {"end_publish", (PyCFunction)lease_end_publish, METH_NOARGS,
     "Every route sent the message: the fence goes up."},
    {"reclaim", (PyCFunction)lease_reclaim, METH_NOARGS,
     "-> WRITABLE when nobody can read the bytes any more; False while held."},
    {"adopt", (PyCFunction)lease_adopt, METH_VARARGS,
     "adopt(block, pool): private memory moved into a pool block."},
    {NULL}
};

static PyMemberDef lease_members[] = {
    {"device", T_OBJECT, offsetof(Lease, device), READONLY, "the Warp device"},
    {"state", T_INT, offsetof(Lease, state), READONLY, "FREE ... PUBLISHED"},
    {"on_cpu", T_BOOL, offsetof(Lease, on_cpu), READONLY, "the memory is host memory"},
    {"rearmable", T_BOOL, offsetof(Lease, rearmable), READONLY, "reclaim may re-arm it"},
    {"__weaklistoffset__", T_PYSSIZET, offsetof(Lease, weakrefs), READONLY},
    {NULL}
};

/* The lease's lock as a context manager (``with lease._lock:``), for code that must exclude the
 * lease's transitions (tests of what may not wait for it). */
typedef struct {
    PyObject_HEAD
    Lease *lease;
} LeaseLock;

static PyTypeObject LeaseLockType;

static void leaselock_dealloc(LeaseLock *self) {
    Py_XDECREF(self->lease);
    PyObject_Free(self);
}

static PyObject *leaselock_enter(LeaseLock *self, PyObject *unused) {
    lease_lock(self->lease);
    return Py_NewRef((PyObject *)self);
}

static PyObject *leaselock_exit(LeaseLock *self, PyObject *args) {
    lease_unlock(self->lease);
    Py_RETURN_FALSE;
}

static PyMethodDef leaselock_methods[] = {
    {"__enter__", (PyCFunction)leaselock_enter, METH_NOARGS, "take the lease's lock"},
    {"__exit__", (PyCFunction)leaselock_exit, METH_VARARGS, "release it"},
    {NULL}
};

static PyTypeObject LeaseLockType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "warp_buffer._core.LeaseLock",
    .tp_basicsize = sizeof(LeaseLock),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_dealloc = (destructor)leaselock_dealloc,
    .tp_methods = leaselock_methods,
};

static PyObject *lease_get_lock(Lease *self, void *closure) {
    LeaseLock *lock = PyObject_New(LeaseLock, &LeaseLockType);
    if (lock != NULL)
        lock->lease = (Lease *)Py_NewRef((PyObject *)self);
    return (PyObject *)lock;
}

static PyGetSetDef lease_getset[] = {
    {"readers", (getter)lease_get_readers, NULL, "tokens alive", NULL},
    {"pool", object_field_get, object_field_set, "gets the block back (None: nobody)",
     OBJECT_FIELD(Lease, pool)},
    {"block", object_field_get, object_field_set, "the block (None: private memory)",
     OBJECT_FIELD(Lease, block)},
    {"writer", object_field_get, object_field_set, "the open write (a WriteState) or None",
     OBJECT_FIELD(Lease, writer)},
    {"event", object_field_get, object_field_set, "CUDA: the last write's completion event",
     OBJECT_FIELD(Lease, event)},
    {"fence", object_field_get, object_field_set,
     "what fences a published lease off from stale writes (a loan's pages) or None",
     OBJECT_FIELD(Lease, fence)},
    {"write_stream", object_field_get, object_field_set,
     "CUDA: the stream a loan's views write on", OBJECT_FIELD(Lease, write_stream)},
    {"_lock", (getter)lease_get_lock, NULL, "the lease's lock, as a context manager", NULL},
    {NULL}
};

PyTypeObject LeaseType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "warp_buffer._core.Lease",
    .tp_doc = "Lease(pool, block, device, rearmable=False): one owner's use of local memory "
              "(warp_buffer.lease).",
    .tp_basicsize = sizeof(Lease),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC | Py_TPFLAGS_BASETYPE,
    .tp_new = lease_new,
    .tp_init = (initproc)lease_init,
    .tp_dealloc = (destructor)lease_dealloc,
    .tp_finalize = (destructor)lease_finalize,
    .tp_traverse = (traverseproc)lease_traverse,
    .tp_clear = (inquiry)lease_clear,
    .tp_repr = (reprfunc)lease_repr,
    .tp_call = lease_call,
    .tp_methods = lease_methods,
    .tp_members = lease_members,
    .tp_getset = lease_getset,
    .tp_weaklistoffset = offsetof(Lease, weakrefs),
};

/* ============================================================================= tokens */
static void token_dealloc(Token *self) {
    Lease *lease = self->lease;
    if (lease != NULL) {
        lease->readers--;
        self->lease = NULL;
        Py_DECREF(lease);
    }
    PyObject_Free(self);
}

static PyObject *token_get_lease(Token *self, void *closure) {
    return Py_NewRef(self->lease ? (PyObject *)self->lease : Py_None);
}

static PyObject *token_call(PyObject *self, PyObject *args, PyObject *kwds) {
    Py_RETURN_NONE;  /* as a wp.array deleter: the array only keeps the token */
}

static PyGetSetDef token_getset[] = {
    {"lease", (getter)token_get_lease, NULL, "the lease it holds", NULL},
    {NULL}
};

PyTypeObject TokenType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "warp_buffer._core.Token",
    .tp_doc = "A reader's hold on a re-armable lease: it ends when the token is gone.",
    .tp_basicsize = sizeof(Token),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_dealloc = (destructor)token_dealloc,
    .tp_call = token_call,
    .tp_getset = token_getset,
};

/* ============================================================================= setup */
/* configure(write_state, complete_write, order_after_write, write_handle_error): the Python
 * pieces the lease calls (warp_buffer.lease). */
PyObject *lease_configure(PyObject *module, PyObject *args) {
    PyObject *ws, *cw, *oa, *err;
    if (!PyArg_ParseTuple(args, "OOOO", &ws, &cw, &oa, &err))
        return NULL;
    Py_XSETREF(WriteStateClass, Py_NewRef(ws));
    Py_XSETREF(CompleteWrite, Py_NewRef(cw));
    Py_XSETREF(OrderAfterWrite, Py_NewRef(oa));
    Py_XSETREF(WriteHandleError, Py_NewRef(err));
    Py_RETURN_NONE;
}

int lease_module_init(PyObject *m) {
    struct { PyObject **slot; const char *text; } names[] = {
        {&str_closed, "closed"}, {&str_sealed, "sealed"}, {&str_stream, "stream"},
        {&str_published, "published"}, {&str_read, "read"}, {&str_core, "core"},
        {&str_give_back, "_give_back"}, {&str_close, "close"}, {&str_protect, "protect"},
        {&str_protected, "protected"}, {&str_try_reclaim, "try_reclaim"},
        {&str_ensure_arena_range, "ensure_arena_range"}, {&str_is_cpu, "is_cpu"},
        {&str_capacity, "capacity"}, {&str_writable, "writable"},
    };
    for (size_t i = 0; i < sizeof names / sizeof *names; i++) {
        *names[i].slot = PyUnicode_InternFromString(names[i].text);
        if (*names[i].slot == NULL)
            return -1;
    }
    PyTypeObject *types[] = {&PeerSlotType, &ArenaCoreType, &ExportsType, &FenceType,
                             &LeaseType, &TokenType};
    const char *type_names[] = {"PeerSlot", "ArenaCore", "Exports", "Fence", "Lease", "Token"};
    if (PyType_Ready(&LeaseLockType) < 0)
        return -1;
    for (size_t i = 0; i < sizeof types / sizeof *types; i++) {
        if (PyType_Ready(types[i]) < 0
                || PyModule_AddObjectRef(m, type_names[i], (PyObject *)types[i]) < 0)
            return -1;
    }
    const char *states[] = {"FREE", "WRITABLE", "WRITING", "WRITTEN", "READ", "PUBLISHED"};
    for (int i = 0; i < 6; i++)
        if (PyModule_AddIntConstant(m, states[i], i) < 0)
            return -1;
    if (PyModule_AddIntConstant(m, "SEQ_BITS", SEQ_BITS) < 0
            || PyModule_AddIntConstant(m, "NO_PEER", ARENA_NO_PEER) < 0)
        return -1;
    return 0;
}
