/* warp_buffer._core: imports (see _core.c): Session, an attached arena, and Hold, an import's
 * token. */
#define PY_SSIZE_T_CLEAN
#define _GNU_SOURCE 1  /* (as pyconfig.h defines it) */
#include <Python.h>
#include <structmember.h>

#include <errno.h>
#include <fcntl.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>
#include <sys/mman.h>
#include <unistd.h>

#include "_core.h"

/* ============================================================================= sessions */

/* live holds of this process per block: offset -> count (open addressing; 0 empty, 1 deleted:
 * offsets are multiples of 4096) */
typedef struct {
    uint64_t *keys;
    uint32_t *counts;
    size_t cap, used, filled;
} holdmap;

static size_t hm_find(const holdmap *m, uint64_t key) {
    size_t mask = m->cap - 1, i = (size_t)((key >> 12) * 0x9E3779B97F4A7C15ULL) & mask;
    while (m->keys[i] != 0 && m->keys[i] != key)
        i = (i + 1) & mask;
    return i;
}

static int hm_grow(holdmap *m) {
    size_t cap = m->cap ? m->cap * 2 : 64;
    holdmap n = {PyMem_Calloc(cap, sizeof(uint64_t)), PyMem_Calloc(cap, sizeof(uint32_t)), cap,
                 0, 0};
    if (n.keys == NULL || n.counts == NULL) {
        PyMem_Free(n.keys);
        PyMem_Free(n.counts);
        PyErr_NoMemory();
        return -1;
    }
    for (size_t i = 0; i < m->cap; i++) {
        if (m->keys[i] > 1) {
            size_t j = hm_find(&n, m->keys[i]);
            n.keys[j] = m->keys[i];
            n.counts[j] = m->counts[i];
            n.used++;
            n.filled++;
        }
    }
    PyMem_Free(m->keys);
    PyMem_Free(m->counts);
    *m = n;
    return 0;
}

/* The count slot of key, inserted (count 0) if missing; NULL on memory error. */
static uint32_t *hm_slot(holdmap *m, uint64_t key) {
    if ((m->filled + 1) * 4 >= m->cap * 3 && hm_grow(m) != 0)
        return NULL;
    size_t mask = m->cap - 1, i = (size_t)((key >> 12) * 0x9E3779B97F4A7C15ULL) & mask;
    size_t tomb = (size_t)-1;
    while (m->keys[i] != 0 && m->keys[i] != key) {
        if (m->keys[i] == 1 && tomb == (size_t)-1)
            tomb = i;
        i = (i + 1) & mask;
    }
    if (m->keys[i] == 0) {
        if (tomb != (size_t)-1)
            i = tomb;
        else
            m->filled++;
        m->keys[i] = key;
        m->counts[i] = 0;
        m->used++;
    }
    return &m->counts[i];
}

static void hm_remove(holdmap *m, uint64_t key) {
    if (m->cap == 0)
        return;
    size_t i = hm_find(m, key);
    if (m->keys[i] == key) {
        m->keys[i] = 1;
        m->counts[i] = 0;
        m->used--;
    }
}

typedef struct {
    PyObject_HEAD
    uint32_t owner_pid;
    uint64_t session;
    int fd;                    /* our own open file description: our locks (-1 once closed) */
    pid_t pid;                 /* the process whose description fd is (a fork shares it) */
    unsigned char *head;       /* header, acknowledgements, generations (writable) */
    size_t head_len;
    unsigned char *data;       /* the blocks (read-only) */
    uint64_t data_offset, data_bytes;
    int owned;                 /* the mappings are ours to unmap (not our own arena's) */
    holdmap holds;
    uint64_t imports;
    PyObject *prev, *next;     /* every live session of this process (sessions_after_fork) */
} Session;

static Session *live_sessions;  /* borrowed: a session leaves the list when it is deallocated */


typedef struct {
    PyObject_HEAD
    Session *session;          /* kept: the mapping lives while a hold does */
    unsigned char *address;
    Py_ssize_t size;
    uint64_t offset;
    int live;
    Py_ssize_t exports;        /* buffer views handed out */
    PyObject *weakrefs;
} Hold;

int lock_range(int fd, short kind, uint64_t offset, uint64_t length) {
    struct flock fl = {.l_type = kind, .l_whence = SEEK_SET, .l_start = (off_t)offset,
                       .l_len = (off_t)length, .l_pid = 0};
    return fcntl(fd, F_OFD_SETLK, &fl);
}

static PyObject *session_new(PyTypeObject *type, PyObject *args, PyObject *kwds) {
    Session *self = (Session *)type->tp_alloc(type, 0);
    if (self != NULL)
        self->fd = -1;
    return (PyObject *)self;
}

/* Session(owner_pid, session, fd, head, head_len, data, data_len, data_offset, owned): the
 * mappings and the description are the session's from now on (unmapped and closed with it;
 * ``owned`` False: our own arena's mappings, only the description is ours). */
static int session_init(Session *self, PyObject *args, PyObject *kwds) {
    static char *kwlist[] = {"owner_pid", "session", "fd", "head", "head_len", "data",
                             "data_len", "data_offset", "owned", NULL};
    unsigned int owner_pid;
    unsigned long long session, head, data, data_len, data_offset, head_len;
    int fd, owned;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "IKiKKKKKp", kwlist, &owner_pid, &session, &fd,
                                     &head, &head_len, &data, &data_len, &data_offset, &owned))
        return -1;
    if (self->head != NULL) {
        PyErr_SetString(PyExc_RuntimeError, "Session initialized twice");
        return -1;
    }
    if (head_len < ARENA_GENS_OFFSET + data_len / ARENA_MIN_BLOCK * 8 || data_offset != head_len
            || data_len == 0 || head == 0 || data == 0) {  /* (a NULL head marks "not linked") */
        PyErr_Format(PyExc_ValueError, "a session of %llu header and %llu data bytes",
                     head_len, data_len);
        return -1;
    }
    self->owner_pid = owner_pid;
    self->session = session;
    self->fd = fd;
    self->pid = this_pid;
    self->head = (unsigned char *)(uintptr_t)head;
    self->head_len = (size_t)head_len;
    self->data = (unsigned char *)(uintptr_t)data;
    self->data_offset = data_offset;
    self->data_bytes = data_len;
    self->owned = owned;
    self->prev = NULL;
    self->next = (PyObject *)live_sessions;
    if (live_sessions != NULL)
        live_sessions->prev = (PyObject *)self;
    live_sessions = self;
    return 0;
}

static void session_dealloc(Session *self) {
    if (self->head != NULL) {  /* off the list of live sessions */
        if (self->prev != NULL)
            ((Session *)self->prev)->next = self->next;
        else if (live_sessions == self)
            live_sessions = (Session *)self->next;
        if (self->next != NULL)
            ((Session *)self->next)->prev = self->prev;
    }
    if (self->owned) {
        if (self->head != NULL)
            munmap(self->head, self->head_len);
        if (self->data != NULL)
            munmap(self->data, self->data_bytes);
    }
    if (self->fd >= 0)
        close(self->fd);  /* its locks go with it */
    PyMem_Free(self->holds.keys);
    PyMem_Free(self->holds.counts);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static inline volatile uint64_t *session_gens(Session *s) {
    return (volatile uint64_t *)(s->head + ARENA_GENS_OFFSET);
}

static inline volatile uint64_t *session_ack(Session *s, unsigned slot) {
    return (volatile uint64_t *)(s->head + ARENA_ACKS_OFFSET + (size_t)slot * ARENA_SLOT_STRIDE);
}

/* One more hold of the block at offset: its lock range read-locked by the first. */
static int session_take(Session *s, uint64_t offset) {
    uint32_t *count = hm_slot(&s->holds, offset);
    if (count == NULL)
        return -1;
    if (*count == 0) {
        if (s->fd < 0 || lock_range(s->fd, F_RDLCK, offset, ARENA_LOCK_SPAN) != 0) {
            int err = errno;
            hm_remove(&s->holds, offset);
            if (s->fd >= 0 && err != EAGAIN && err != EACCES) {
                errno = err;
                raise_as(ExportError, PyExc_OSError, "cannot hold block %#llx of process %u: %s",
                         (unsigned long long)offset, s->owner_pid, strerror(err));
                return -1;
            }
            raise_as(RecycledBufferError, PyExc_RuntimeError,
                     "block %#llx of process %u is being recycled", (unsigned long long)offset,
                     s->owner_pid);
            return -1;
        }
    }
    (*count)++;
    return 0;
}

/* One hold of the block at offset ends: the last unlocks its range. Never fails; no Python. */
static void session_drop(Session *s, uint64_t offset) {
    if (s->holds.cap == 0)
        return;
    size_t i = hm_find(&s->holds, offset);
    if (s->holds.keys[i] != offset)
        return;
    if (--s->holds.counts[i] == 0) {
        hm_remove(&s->holds, offset);
        /* Not in a forked child that kept its parent's description (the lock is the parent's
         * too), nor on a closed one. */
        if (s->fd >= 0 && s->pid == this_pid)
            lock_range(s->fd, F_UNLCK, offset, ARENA_LOCK_SPAN);
    }
}

static PyObject *new_hold(Session *s, uint64_t offset, uint64_t size) {
    Hold *hold = PyObject_New(Hold, &HoldType);
    if (hold == NULL)
        return NULL;
    Py_INCREF(s);
    hold->session = s;
    hold->address = s->data + (offset - s->data_offset);
    hold->size = (Py_ssize_t)size;
    hold->offset = offset;
    hold->live = 1;
    hold->exports = 0;
    hold->weakrefs = NULL;
    return (PyObject *)hold;
}

/* The fields a descriptor names its export with (up to device_uuid), each checked to fit its
 * width (the handles too), then: the version, the kind, a pid, a session and a generation, a
 * peer slot. */
static int check_descriptor_values(PyObject *values, uint64_t *v) {
    PyObject *seq = PySequence_Fast(values, "descriptor values must be a sequence");
    if (seq == NULL)
        return -1;
    if (PySequence_Fast_GET_SIZE(seq) != DESC_FIELDS) {
        Py_DECREF(seq);
        descriptor_error("a descriptor has %d fields", DESC_FIELDS);
        return -1;
    }
    for (int i = 0; i < DESC_FIELDS; i++) {
        uint64_t value;
        if (field_value(PySequence_Fast_GET_ITEM(seq, i), i, &value) != 0) {
            Py_DECREF(seq);
            return -1;
        }
        if (i < DESC_FIELD_COUNT_USED)
            v[i] = value;
    }
    Py_DECREF(seq);
    if (v[F_VERSION] != DESC_VERSION) {
        descriptor_error("descriptor version %llu (this reader knows %d)",
                         (unsigned long long)v[F_VERSION], DESC_VERSION);
        return -1;
    }
    if (v[F_KIND] > DESC_KIND_CUDA_VMM) {
        descriptor_error("unknown descriptor kind %llu", (unsigned long long)v[F_KIND]);
        return -1;
    }
    if (v[F_PID] == 0 || v[F_PID] >= PID_MAX || v[F_SESSION] == 0 || v[F_GENERATION] == 0) {
        descriptor_error("descriptor names no export (pid %llu, session %#llx, generation %llu)",
                         (unsigned long long)v[F_PID], (unsigned long long)v[F_SESSION],
                         (unsigned long long)v[F_GENERATION]);
        return -1;
    }
    if (v[F_SLOT] != ARENA_NO_PEER && v[F_SLOT] >= ARENA_MAX_PEERS) {
        descriptor_error("peer slot %llu", (unsigned long long)v[F_SLOT]);
        return -1;
    }
    return 0;
}

/* check_names(values): raise DescriptorError unless the values name an export (what an import
 * checks before it attaches to the session they name). */
PyObject *check_names(PyObject *module, PyObject *values) {
    uint64_t v[DESC_FIELD_COUNT_USED];
    if (check_descriptor_values(values, v) != 0)
        return NULL;
    Py_RETURN_NONE;
}

/* import_block(values) -> Hold: the import of the descriptor whose 27 field values are given
 * (warp_buffer.descriptor.FIELDS order), checked against this session: version, kind, the
 * names of the export, the peer slot, the block's place in the geometry (a CUDA block's lock
 * range: one MIN_BLOCK), its size; then held, acknowledged (also when the hold fails: the
 * descriptor was consumed), and its generation compared. */
static PyObject *session_import_block(Session *self, PyObject *values) {
    uint64_t v[DESC_FIELD_COUNT_USED];
    if (check_descriptor_values(values, v) != 0)
        return NULL;
    if (v[F_PID] != self->owner_pid || v[F_SESSION] != self->session)
        return descriptor_error("descriptor of session %#llx of process %llu imported through "
                                "session %#llx of process %u", (unsigned long long)v[F_SESSION],
                                (unsigned long long)v[F_PID], (unsigned long long)self->session,
                                self->owner_pid);
    unsigned slot = (unsigned)v[F_SLOT];
    int cuda = v[F_KIND] == DESC_KIND_CUDA_IPC || v[F_KIND] == DESC_KIND_CUDA_VMM;
    uint64_t offset = v[F_OFFSET], capacity = v[F_CAPACITY], size = v[F_SIZE];
    uint64_t block = cuda ? ARENA_MIN_BLOCK : capacity;
    if (block < ARENA_MIN_BLOCK || (block & (block - 1)) || block > self->data_bytes)
        return raise_as(ExportBoundsError, PyExc_ValueError, "descriptor of process %u: "
                        "capacity %llu is not a block size of this arena", self->owner_pid,
                        (unsigned long long)block);
    if (offset < self->data_offset || (offset - self->data_offset) % block
            || offset - self->data_offset > self->data_bytes - block)
        return raise_as(ExportBoundsError, PyExc_ValueError, "descriptor of process %u: "
                        "offset %llu is not the start of a %llu-byte block", self->owner_pid,
                        (unsigned long long)offset, (unsigned long long)block);
    if (size == 0 || size > capacity || (!cuda && size > block))
        return raise_as(ExportBoundsError, PyExc_ValueError, "size %llu outside 1..%llu",
                        (unsigned long long)size, (unsigned long long)capacity);
    int held = session_take(self, offset);
    if (slot != ARENA_NO_PEER) {  /* after the lock: the publisher's probe then meets it */
        volatile uint64_t *ack = session_ack(self, slot);
        if (*ack < v[F_SEQUENCE])
            *ack = v[F_SEQUENCE];
    }
    if (held != 0)
        return NULL;
    PyObject *hold = new_hold(self, offset, cuda ? ARENA_MIN_BLOCK : size);
    if (hold == NULL) {
        session_drop(self, offset);
        return NULL;
    }
    uint64_t generation = session_gens(self)[(offset - self->data_offset) / ARENA_MIN_BLOCK];
    if (generation != v[F_GENERATION]) {
        Py_DECREF(hold);
        /* Generations only grow: one the block has left behind (or a free block's 0) is a
         * recycled export; any other names an export that never was (forged or corrupt). */
        if (generation == 0 || generation >> ARENA_GENERATION_ORDER_BITS
                               > v[F_GENERATION] >> ARENA_GENERATION_ORDER_BITS)
            return raise_as(RecycledBufferError, PyExc_RuntimeError, "block %#llx of process %u "
                            "was recycled (a later publish reuses it)",
                            (unsigned long long)offset, self->owner_pid);
        return raise_as(StaleBufferError, PyExc_RuntimeError, "block %#llx of process %u holds "
                        "no export of generation %#llx", (unsigned long long)offset,
                        self->owner_pid, (unsigned long long)v[F_GENERATION]);
    }
    uint64_t order = 63 - (uint64_t)__builtin_clzll(capacity);
    if ((generation & ((1u << ARENA_GENERATION_ORDER_BITS) - 1)) != order) {
        Py_DECREF(hold);
        return raise_as(ExportBoundsError, PyExc_ValueError, "descriptor of process %u: "
                        "capacity %llu is not that of block %#llx", self->owner_pid,
                        (unsigned long long)capacity, (unsigned long long)offset);
    }
    self->imports++;
    return hold;
}

/* In a forked child: move this process's holds onto a description of its own (the inherited
 * one is shared with the parent, whose unlocks would end ours and ours its). */
static PyObject *session_take_own_locks(Session *self, PyObject *unused) {
    if (self->fd < 0 || self->pid == this_pid)
        Py_RETURN_NONE;
    char path[64];
    snprintf(path, sizeof path, "/proc/self/fd/%d", self->fd);
    int fd = open(path, O_RDWR | O_CLOEXEC);
    if (fd < 0)
        Py_RETURN_NONE;  /* out of fds: the shared description stays (the parent's locks cover) */
    for (size_t i = 0; i < self->holds.cap; i++)
        if (self->holds.keys[i] > 1)
            lock_range(fd, F_RDLCK, self->holds.keys[i], ARENA_LOCK_SPAN);
    close(self->fd);
    self->fd = fd;
    self->pid = this_pid;
    Py_RETURN_NONE;
}

/* sessions_after_fork(): in a forked child, every live session's holds move onto a description
 * of the child's own (what warp_buffer.attach's fork hook calls). */
PyObject *sessions_after_fork(PyObject *module, PyObject *unused) {
    for (Session *s = live_sessions; s != NULL; s = (Session *)s->next) {
        PyObject *r = session_take_own_locks(s, NULL);
        if (r == NULL)
            return NULL;
        Py_DECREF(r);
    }
    Py_RETURN_NONE;
}

static PyObject *session_generation(Session *self, PyObject *arg) {
    unsigned long long offset = PyLong_AsUnsignedLongLong(arg);
    if (offset == (unsigned long long)-1 && PyErr_Occurred())
        return NULL;
    if (offset < self->data_offset || offset - self->data_offset >= self->data_bytes)
        return raise_as(ExportBoundsError, PyExc_ValueError, "offset %llu", offset);
    return PyLong_FromUnsignedLongLong(
        session_gens(self)[(offset - self->data_offset) / ARENA_MIN_BLOCK]);
}

static PyObject *session_ack_of(Session *self, PyObject *arg) {
    long slot = PyLong_AsLong(arg);
    if (slot == -1 && PyErr_Occurred())
        return NULL;
    if (slot < 0 || slot >= ARENA_MAX_PEERS)
        return raise_as(DescriptorError, PyExc_ValueError, "peer slot %ld", slot);
    return PyLong_FromUnsignedLongLong(*session_ack(self, (unsigned)slot));
}

static PyObject *session_get_held(Session *self, void *closure) {
    return PyLong_FromSize_t(self->holds.used);
}

static PyObject *session_get_address(Session *self, void *closure) {
    return PyLong_FromVoidPtr(self->data);
}

static PyMethodDef session_methods[] = {
    {"import_block", (PyCFunction)session_import_block, METH_O,
     "import_block(values) -> Hold: check, hold and acknowledge the block a descriptor names."},
    {"take_own_locks", (PyCFunction)session_take_own_locks, METH_NOARGS,
     "In a forked child: the holds move onto a description of this process's own."},
    {"generation", (PyCFunction)session_generation, METH_O,
     "generation(offset) -> int: the generation word of the block at offset."},
    {"ack", (PyCFunction)session_ack_of, METH_O,
     "ack(slot) -> int: the last delivery this process acknowledged on a peer slot."},
    {NULL}
};

static PyMemberDef session_members[] = {
    {"owner_pid", T_UINT, offsetof(Session, owner_pid), READONLY, "the publisher's pid"},
    {"session", T_ULONGLONG, offsetof(Session, session), READONLY, "the session tag"},
    {"fd", T_INT, offsetof(Session, fd), READONLY, "our description (-1: closed)"},
    {"data_offset", T_ULONGLONG, offsetof(Session, data_offset), READONLY, "file offset of data"},
    {"data_bytes", T_ULONGLONG, offsetof(Session, data_bytes), READONLY, "bytes of data"},
    {"imports", T_ULONGLONG, offsetof(Session, imports), READONLY, "imports so far"},
    {NULL}
};

static PyGetSetDef session_getset[] = {
    {"held", (getter)session_get_held, NULL, "blocks held by this process now", NULL},
    {"data_address", (getter)session_get_address, NULL, "where the data is mapped here", NULL},
    {NULL}
};

PyTypeObject SessionType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "warp_buffer._core.Session",
    .tp_doc = "Session(owner_pid, session, fd, head, head_len, data, data_len, data_offset, "
              "owned): a publisher's arena as this process maps it, and imports from it.",
    .tp_basicsize = sizeof(Session),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = session_new,
    .tp_init = (initproc)session_init,
    .tp_dealloc = (destructor)session_dealloc,
    .tp_methods = session_methods,
    .tp_members = session_members,
    .tp_getset = session_getset,
};

/* ============================================================================= holds */

static void hold_end(Hold *self) {
    if (self->live) {
        self->live = 0;
        session_drop(self->session, self->offset);
    }
}

static void hold_dealloc(Hold *self) {
    if (self->weakrefs != NULL)
        PyObject_ClearWeakRefs((PyObject *)self);
    hold_end(self);
    Py_CLEAR(self->session);
    PyObject_Free(self);
}

static PyObject *hold_release(Hold *self, PyObject *unused) {
    hold_end(self);
    Py_RETURN_NONE;
}

/* As a wp.array deleter (ptr, size): the array only keeps the hold alive. */
static PyObject *hold_call(PyObject *self, PyObject *args, PyObject *kwds) {
    Py_RETURN_NONE;
}

static int hold_getbuffer(Hold *self, Py_buffer *view, int flags) {
    if (!self->live) {  /* its lock is gone: the publisher may reuse the bytes */
        PyErr_SetString(PyExc_BufferError, "the hold was released");
        view->obj = NULL;
        return -1;
    }
    if (flags & PyBUF_WRITABLE) {
        PyErr_SetString(PyExc_BufferError, "an imported block is read-only");
        view->obj = NULL;
        return -1;
    }
    if (PyBuffer_FillInfo(view, (PyObject *)self, self->address, self->size, 1, flags) != 0)
        return -1;
    self->exports++;
    return 0;
}

static void hold_releasebuffer(Hold *self, Py_buffer *view) {
    self->exports--;
}

static PyBufferProcs hold_as_buffer = {
    .bf_getbuffer = (getbufferproc)hold_getbuffer,
    .bf_releasebuffer = (releasebufferproc)hold_releasebuffer,
};

/* -- DLPack (v1.0 ABI; legacy capsules for consumers that ask for no version) -------------- */
typedef struct { uint32_t major, minor; } DLPackVersion;
typedef struct { int32_t device_type, device_id; } DLDevice;
typedef struct { uint8_t code, bits; uint16_t lanes; } DLDataType;
typedef struct {
    void *data;
    DLDevice device;
    int32_t ndim;
    DLDataType dtype;
    int64_t *shape, *strides;
    uint64_t byte_offset;
} DLTensor;
typedef struct DLManagedTensor {
    DLTensor dl_tensor;
    void *manager_ctx;
    void (*deleter)(struct DLManagedTensor *);
} DLManagedTensor;
typedef struct DLManagedTensorVersioned {
    DLPackVersion version;
    void *manager_ctx;
    void (*deleter)(struct DLManagedTensorVersioned *);
    uint64_t flags;
    DLTensor dl_tensor;
} DLManagedTensorVersioned;
#define DLPACK_FLAG_READ_ONLY 1ULL
#define DL_CPU 1
#define DL_UINT 1

typedef struct {
    DLManagedTensor legacy;
    DLManagedTensorVersioned versioned;
    int64_t shape[1];
} dl_export;

static void drop_manager(void *ctx) {
    if (!Py_IsInitialized())
        return;  /* the interpreter is gone: the process is exiting */
    PyGILState_STATE gil = PyGILState_Ensure();
    Py_DECREF((PyObject *)ctx);
    PyGILState_Release(gil);
}

static void dl_legacy_deleter(DLManagedTensor *t) {
    dl_export *e = (dl_export *)t;
    drop_manager(t->manager_ctx);
    PyMem_RawFree(e);
}

static void dl_versioned_deleter(DLManagedTensorVersioned *t) {
    dl_export *e = (dl_export *)((char *)t - offsetof(dl_export, versioned));
    drop_manager(t->manager_ctx);
    PyMem_RawFree(e);
}

static void dl_capsule_destructor(PyObject *capsule) {
    /* A capsule a consumer took was renamed "used_dltensor*": its deleter is the consumer's. */
    if (PyCapsule_IsValid(capsule, "dltensor")) {
        DLManagedTensor *t = PyCapsule_GetPointer(capsule, "dltensor");
        t->deleter(t);
    } else if (PyCapsule_IsValid(capsule, "dltensor_versioned")) {
        DLManagedTensorVersioned *t = PyCapsule_GetPointer(capsule, "dltensor_versioned");
        t->deleter(t);
    }
    PyErr_Clear();
}

/* __dlpack__(*, stream=None, max_version=None, dl_device=None, copy=None): a capsule over the
 * block (1-D uint8, read-only: versioned capsules say so), holding a reference to this hold
 * until the consumer's tensor is gone. */
static PyObject *hold_dlpack(Hold *self, PyObject *args, PyObject *kwds) {
    static char *kwlist[] = {"stream", "max_version", "dl_device", "copy", NULL};
    PyObject *stream = Py_None, *max_version = Py_None, *dl_device = Py_None, *copy = Py_None;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "|$OOOO", kwlist, &stream, &max_version,
                                     &dl_device, &copy))
        return NULL;
    if (!self->live) {
        PyErr_SetString(PyExc_BufferError, "the hold was released");
        return NULL;
    }
    if (stream != Py_None) {  /* the one stream a cpu consumer may pass: -1 */
        int overflow = 0;
        long value = PyLong_Check(stream) ? PyLong_AsLongAndOverflow(stream, &overflow) : 0;
        if (value == -1 && PyErr_Occurred())
            return NULL;
        if (!PyLong_Check(stream) || overflow || value != -1) {
            PyErr_SetString(PyExc_BufferError, "a cpu block takes no stream");
            return NULL;
        }
    }
    if (copy == Py_True) {
        PyErr_SetString(PyExc_BufferError, "the block is exported without a copy");
        return NULL;
    }
    if (dl_device != Py_None) {
        int type = 0, id = 0;
        if (!PyArg_ParseTuple(dl_device, "ii", &type, &id))
            return NULL;
        if (type != DL_CPU || id != 0) {
            PyErr_SetString(PyExc_BufferError, "the block lives on the cpu");
            return NULL;
        }
    }
    int versioned = 0;
    if (max_version != Py_None) {
        unsigned int major = 0, minor = 0;
        if (!PyArg_ParseTuple(max_version, "II", &major, &minor))
            return NULL;
        versioned = major >= 1;
    }
    dl_export *e = PyMem_RawCalloc(1, sizeof(dl_export));
    if (e == NULL)
        return PyErr_NoMemory();
    e->shape[0] = self->size;
    DLTensor tensor = {.data = self->address, .device = {DL_CPU, 0}, .ndim = 1,
                       .dtype = {DL_UINT, 8, 1}, .shape = e->shape, .strides = NULL,
                       .byte_offset = 0};
    PyObject *capsule;
    Py_INCREF(self);
    if (versioned) {
        e->versioned.version = (DLPackVersion){1, 0};
        e->versioned.manager_ctx = self;
        e->versioned.deleter = dl_versioned_deleter;
        e->versioned.flags = DLPACK_FLAG_READ_ONLY;
        e->versioned.dl_tensor = tensor;
        capsule = PyCapsule_New(&e->versioned, "dltensor_versioned", dl_capsule_destructor);
    } else {
        e->legacy.dl_tensor = tensor;
        e->legacy.manager_ctx = self;
        e->legacy.deleter = dl_legacy_deleter;
        capsule = PyCapsule_New(&e->legacy, "dltensor", dl_capsule_destructor);
    }
    if (capsule == NULL) {
        Py_DECREF(self);
        PyMem_RawFree(e);
    }
    return capsule;
}

static PyObject *hold_dlpack_device(Hold *self, PyObject *unused) {
    return Py_BuildValue("(ii)", DL_CPU, 0);
}

static PyObject *hold_get_address(Hold *self, void *closure) {
    return PyLong_FromVoidPtr(self->address);
}

static PyObject *hold_get_live(Hold *self, void *closure) {
    return PyBool_FromLong(self->live);
}

static PyObject *hold_get_session(Hold *self, void *closure) {
    return Py_NewRef((PyObject *)self->session);
}

static Py_ssize_t hold_length(Hold *self) {
    return self->size;
}

static PySequenceMethods hold_as_sequence = {.sq_length = (lenfunc)hold_length};

static PyMethodDef hold_methods[] = {
    {"release", (PyCFunction)hold_release, METH_NOARGS,
     "End the hold now (idempotent). What still reads the bytes then reads memory the "
     "publisher may reuse: drop every reference instead where you can."},
    {"__dlpack__", (PyCFunction)(void (*)(void))hold_dlpack, METH_VARARGS | METH_KEYWORDS,
     "A DLPack capsule over the block (read-only), keeping the hold while it is used."},
    {"__dlpack_device__", (PyCFunction)hold_dlpack_device, METH_NOARGS, "(kDLCPU, 0)"},
    {NULL}
};

static PyMemberDef hold_members[] = {
    {"offset", T_ULONGLONG, offsetof(Hold, offset), READONLY, "the block's file offset"},
    {"size", T_PYSSIZET, offsetof(Hold, size), READONLY, "bytes readable"},
    {"__weaklistoffset__", T_PYSSIZET, offsetof(Hold, weakrefs), READONLY},
    {NULL}
};

static PyGetSetDef hold_getset[] = {
    {"address", (getter)hold_get_address, NULL, "where the bytes are in this process", NULL},
    {"live", (getter)hold_get_live, NULL, "the hold has not ended", NULL},
    {"session", (getter)hold_get_session, NULL, "the session it holds a block of", NULL},
    {NULL}
};

PyTypeObject HoldType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "warp_buffer._core.Hold",
    .tp_doc = "One import's hold on a publisher's block (see the module docstring).",
    .tp_basicsize = sizeof(Hold),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_dealloc = (destructor)hold_dealloc,
    .tp_call = hold_call,
    .tp_as_buffer = &hold_as_buffer,
    .tp_as_sequence = &hold_as_sequence,
    .tp_methods = hold_methods,
    .tp_members = hold_members,
    .tp_getset = hold_getset,
    .tp_weaklistoffset = offsetof(Hold, weakrefs),
};

