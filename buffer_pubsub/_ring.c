/* buffer_pubsub._ring: the same-host lane's native core.
 *
 * A ring is one sealed anonymous memfd that its writer (a publisher's route to one subscription)
 * creates, maps and hands to the reader over a Unix socket with an eventfd, the doorbell
 * (buffer_pubsub.fast_lane does the hand-over). Nothing has a name: a crash leaves nothing the
 * kernel does not reclaim. One writer and one reader per ring; keep-last: a writer never waits,
 * it overwrites the oldest frame when the reader is a whole ring behind.
 *
 * Layout (native byte order: one host):
 *   [0, 4096)      header: magic, version, depth, slot_bytes, writer pid;
 *                  line 1 (writer's): tail (frames published), writer_closed;
 *                  line 2 (reader's): head (frames taken, a hint), waiting, reader_closed
 *   [4096, ...)    depth slots of slot_bytes: stamp (u64), length (u32), pad, data
 *
 * A slot's stamp is 2n+1 while frame n is written into it, 2n+2 once it is complete (a seqlock:
 * the reader copies the frame out and checks the stamp again). The reader trusts nothing it
 * reads from the ring: lengths are bounded by its own copy of the geometry, indexes by its own
 * count, and every loop by the depth. The writer trusts nothing the reader writes either (the
 * reader's words are hints: waiting, closed).
 *
 * The doorbell: before it sleeps the reader sets `waiting` and checks the tail again; the writer
 * publishes the tail and rings only when it swaps `waiting` from 1 to 0 (one eventfd write per
 * sleep, none while the reader is busy).
 *
 * Waker: one thread's wait primitive (the node's executor): an eventfd for notify(), the
 * doorbells of the rings it drains, and other fds the Python layer watches (listening and
 * connection sockets). The GIL is released only inside ppoll() and the optional busy-poll spin.
 */
#define PY_SSIZE_T_CLEAN
#define _GNU_SOURCE 1  /* (as pyconfig.h defines it) */
#include <Python.h>
#include <structmember.h>

#include <errno.h>
#include <pthread.h>
#include <fcntl.h>
#include <limits.h>
#include <poll.h>
#include <sched.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>
#include <sys/eventfd.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#include "_ring.h"

/* ----------------------------------------------------------------------------- this process */
/* Our pid, kept across forks by pthread_atfork: the per-message checks "is this still the
 * process that made it?" cost no system call (glibc does not cache getpid). */
static pid_t this_pid;

static void refresh_pid(void) {
    this_pid = getpid();
}

/* ----------------------------------------------------------------------------- errors */
static PyObject *RingError;  /* set by the module init from buffer_pubsub.fast_lane's class */

/* Raise the lane's error class with a message formatted by C's printf. */
static PyObject *ring_error(const char *fmt, ...) {
    char text[512];
    va_list args;
    va_start(args, fmt);
    vsnprintf(text, sizeof text, fmt, args);
    va_end(args);
    PyErr_SetString(RingError ? RingError : PyExc_RuntimeError, text);
    return NULL;
}

static PyObject *ring_oserror(const char *what) {
    int err = errno;
    return ring_error("%s: %s", what, strerror(err));
}

/* ----------------------------------------------------------------------------- writer */
typedef struct {
    PyObject_HEAD
    unsigned char *map;   /* NULL once closed */
    size_t size;
    uint32_t depth, slot_bytes;
    uint32_t max_frame;   /* the largest frame write() takes (at most a slot's room) */
    uint64_t tail;        /* our own count: never read back from the ring */
    int memfd;            /* -1 once handed over (take_memfd) */
    int doorbell;         /* eventfd, -1 once closed */
    pid_t pid;            /* the process that made it: a forked child must not write */
    uint64_t rings;       /* doorbell writes (the reader was asleep) */
    int conn;             /* the reader's connection (not ours to close), -1: none */
    int reader_gone;      /* its connection hung up: frames reach nobody */
} RingWriter;

static int writer_init(RingWriter *self, PyObject *args, PyObject *kwds) {
    static char *kwlist[] = {"depth", "slot_bytes", "max_frame", NULL};
    unsigned int depth = 16, slot_bytes = RING_DEFAULT_SLOT, max_frame = 0;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "|III", kwlist, &depth, &slot_bytes,
                                     &max_frame))
        return -1;
    if (self->map != NULL || self->memfd >= 0) {
        PyErr_SetString(PyExc_RuntimeError, "RingWriter initialized twice");
        return -1;
    }
    if (!ring_geometry_ok(depth, slot_bytes)) {
        PyErr_Format(PyExc_ValueError, "ring of %u slots of %u bytes", depth, slot_bytes);
        return -1;
    }
    size_t size = ring_file_size(depth, slot_bytes);
    int fd = memfd_create("warp_buffer_lane", MFD_CLOEXEC | MFD_ALLOW_SEALING);
    if (fd < 0) {
        ring_oserror("no memfd for a lane ring");
        return -1;
    }
    if (fchmod(fd, 0600) != 0 || ftruncate(fd, (off_t)size) != 0
            || fcntl(fd, F_ADD_SEALS, RING_SEALS) != 0) {
        ring_oserror("cannot size and seal a lane ring");
        close(fd);
        return -1;
    }
    void *map = mmap(NULL, size, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
    if (map == MAP_FAILED) {
        ring_oserror("cannot map a lane ring");
        close(fd);
        return -1;
    }
    int bell = eventfd(0, EFD_CLOEXEC | EFD_NONBLOCK);
    if (bell < 0) {
        ring_oserror("no eventfd for a lane ring");
        munmap(map, size);
        close(fd);
        return -1;
    }
    ring_header_init((ring_header *)map, depth, slot_bytes, (uint32_t)this_pid);
    self->map = map;
    self->size = size;
    self->depth = depth;
    self->slot_bytes = slot_bytes;
    self->max_frame = max_frame == 0 || max_frame > slot_bytes - RING_SLOT_HEAD
                      ? slot_bytes - RING_SLOT_HEAD : max_frame;
    self->tail = 0;
    self->memfd = fd;
    self->doorbell = bell;
    self->pid = this_pid;
    return 0;
}

static PyObject *writer_new(PyTypeObject *type, PyObject *args, PyObject *kwds) {
    RingWriter *self = (RingWriter *)type->tp_alloc(type, 0);
    if (self != NULL) {
        self->memfd = -1;
        self->doorbell = -1;
        self->conn = -1;
    }
    return (PyObject *)self;
}

/* Is the reader gone? Asked only when it is a whole ring behind (slow, frozen or dead): one
 * poll() then, none while it keeps up. A reader that closed its end says so in the ring. */
static int writer_reader_gone(RingWriter *self, ring_header *h) {
    if (self->reader_gone || __atomic_load_n(&h->reader_closed, __ATOMIC_RELAXED))
        return 1;
    if (self->conn < 0)
        return 0;
    uint64_t head = __atomic_load_n(&h->head, __ATOMIC_RELAXED);
    if (head <= self->tail && self->tail - head < self->depth)
        return 0;
    struct pollfd p = {.fd = self->conn, .events = 0};
    if (poll(&p, 1, 0) == 1 && (p.revents & (POLLHUP | POLLERR | POLLNVAL)))
        self->reader_gone = 1;
    return self->reader_gone;
}

static void writer_release(RingWriter *self) {
    if (self->map != NULL) {
        ring_header *h = (ring_header *)self->map;
        if (self->pid == this_pid) {
            __atomic_store_n(&h->writer_closed, 1, __ATOMIC_SEQ_CST);
            if (self->doorbell >= 0) {  /* wake the reader: it drains and lets the ring go */
                uint64_t one = 1;
                ssize_t ignored = write(self->doorbell, &one, sizeof one);
                (void)ignored;
            }
        }
        munmap(self->map, self->size);
        self->map = NULL;
    }
    self->conn = -1;
    if (self->memfd >= 0) {
        close(self->memfd);
        self->memfd = -1;
    }
    if (self->doorbell >= 0) {
        close(self->doorbell);
        self->doorbell = -1;
    }
}

static void writer_dealloc(RingWriter *self) {
    writer_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject *writer_close(RingWriter *self, PyObject *unused) {
    writer_release(self);
    Py_RETURN_NONE;
}

/* write(*parts) -> bool: one frame, the concatenation of parts (bytes-like). False when the
 * reader closed its end (the frame reached nobody). Never blocks. */
static PyObject *writer_write(RingWriter *self, PyObject *const *args, Py_ssize_t nargs) {
    if (self->map == NULL)
        return ring_error("the lane ring is closed");
    if (self->pid != this_pid)
        return ring_error("the lane ring belongs to process %d (this is a fork of it)",
                          (int)self->pid);
    ring_header *h = (ring_header *)self->map;
    if (writer_reader_gone(self, h))
        Py_RETURN_FALSE;
    Py_buffer views[4];
    if (nargs > 4) {
        PyErr_SetString(PyExc_TypeError, "a lane frame has at most 4 parts");
        return NULL;
    }
    Py_ssize_t total = 0, got = 0;
    for (; got < nargs; got++) {
        if (PyObject_GetBuffer(args[got], &views[got], PyBUF_SIMPLE) != 0)
            goto fail;
        total += views[got].len;
    }
    if (total > (Py_ssize_t)self->max_frame) {
        ring_error("%zd B message exceeds the lane's %u B", total, self->max_frame);
        goto fail;
    }
    uint64_t n = self->tail;
    ring_slot *slot = ring_slot_at(self->map, self->depth, self->slot_bytes, n);
    __atomic_store_n(&slot->stamp, 2 * n + 1, __ATOMIC_RELAXED);
    __atomic_thread_fence(__ATOMIC_RELEASE);
    unsigned char *out = slot->data;
    for (Py_ssize_t i = 0; i < nargs; i++) {
        memcpy(out, views[i].buf, (size_t)views[i].len);
        out += views[i].len;
        PyBuffer_Release(&views[i]);
    }
    slot->length = (uint32_t)total;
    __atomic_store_n(&slot->stamp, 2 * n + 2, __ATOMIC_RELEASE);
    self->tail = n + 1;
    __atomic_store_n(&h->tail, n + 1, __ATOMIC_SEQ_CST);
    /* Dekker with the reader's wait: it sets waiting, then reads the tail; we published the
     * tail, then read waiting. One of us sees the other. */
    if (__atomic_load_n(&h->waiting, __ATOMIC_SEQ_CST)
            && __atomic_exchange_n(&h->waiting, 0, __ATOMIC_SEQ_CST)) {
        uint64_t one = 1;
        self->rings++;
        if (write(self->doorbell, &one, sizeof one) < 0 && errno != EAGAIN)
            return ring_oserror("lane doorbell");
    }
    Py_RETURN_TRUE;
fail:
    for (Py_ssize_t i = 0; i < got; i++)
        PyBuffer_Release(&views[i]);
    return NULL;
}

static PyObject *writer_fits(RingWriter *self, PyObject *arg) {
    Py_ssize_t n = PyLong_AsSsize_t(arg);
    if (n == -1 && PyErr_Occurred())
        return NULL;
    return PyBool_FromLong(n >= 0 && n <= (Py_ssize_t)self->max_frame);
}

/* take_memfd() -> int: the ring's memfd, now the caller's (to send, then close). */
static PyObject *writer_take_memfd(RingWriter *self, PyObject *unused) {
    int fd = self->memfd;
    self->memfd = -1;
    return PyLong_FromLong(fd);
}

/* watch(fd): the reader's connection, polled for a hang-up when the reader falls a whole
 * ring behind (the caller keeps it open while the writer lives). */
static PyObject *writer_watch(RingWriter *self, PyObject *arg) {
    long fd = PyLong_AsLong(arg);
    if (fd == -1 && PyErr_Occurred())
        return NULL;
    if (fd < -1 || fd > INT_MAX)
        return PyErr_Format(PyExc_ValueError, "watch(fd): %ld is not a file descriptor", fd);
    self->conn = (int)fd;
    Py_RETURN_NONE;
}

static PyObject *writer_reader_closed(RingWriter *self, void *closure) {
    if (self->map == NULL)
        Py_RETURN_TRUE;
    return PyBool_FromLong(__atomic_load_n(&((ring_header *)self->map)->reader_closed,
                                           __ATOMIC_RELAXED) != 0 || self->reader_gone);
}

static PyObject *writer_backlog(RingWriter *self, void *closure) {
    /* frames the reader has not taken (its head is a hint: clamped to [0, depth]) */
    if (self->map == NULL)
        return PyLong_FromLong(0);
    uint64_t head = __atomic_load_n(&((ring_header *)self->map)->head, __ATOMIC_RELAXED);
    uint64_t behind = head > self->tail ? 0 : self->tail - head;
    return PyLong_FromUnsignedLongLong(behind > self->depth ? self->depth : behind);
}

static PyMethodDef writer_methods[] = {
    {"write", (PyCFunction)(void (*)(void))writer_write, METH_FASTCALL,
     "write(*parts) -> bool: publish one frame; False when the reader closed its end."},
    {"fits", (PyCFunction)writer_fits, METH_O, "fits(nbytes) -> bool"},
    {"watch", (PyCFunction)writer_watch, METH_O,
     "watch(fd): the reader's connection, checked for a hang-up when it is a ring behind."},
    {"take_memfd", (PyCFunction)writer_take_memfd, METH_NOARGS,
     "The ring's memfd, the caller's from now on (-1 once taken)."},
    {"close", (PyCFunction)writer_close, METH_NOARGS,
     "Mark the ring closed, ring the doorbell, unmap it (idempotent)."},
    {NULL}
};

static PyMemberDef writer_members[] = {
    {"doorbell", T_INT, offsetof(RingWriter, doorbell), READONLY, "the eventfd (-1: closed)"},
    {"depth", T_UINT, offsetof(RingWriter, depth), READONLY, "slots"},
    {"slot_bytes", T_UINT, offsetof(RingWriter, slot_bytes), READONLY, "bytes per slot"},
    {"max_frame", T_UINT, offsetof(RingWriter, max_frame), READONLY, "largest frame"},
    {"size", T_PYSSIZET, offsetof(RingWriter, size), READONLY, "bytes of the memfd"},
    {"written", T_ULONGLONG, offsetof(RingWriter, tail), READONLY, "frames written"},
    {"rings", T_ULONGLONG, offsetof(RingWriter, rings), READONLY, "doorbell writes"},
    {NULL}
};

static PyGetSetDef writer_getset[] = {
    {"reader_closed", (getter)writer_reader_closed, NULL, "the reader closed its end", NULL},
    {"backlog", (getter)writer_backlog, NULL, "frames not taken yet (a hint)", NULL},
    {NULL}
};

static PyTypeObject RingWriterType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "buffer_pubsub._ring.RingWriter",
    .tp_doc = "RingWriter(depth=16, slot_bytes=8256, max_frame=0): the writing end of a new lane "
              "ring (max_frame 0: a whole slot).",
    .tp_basicsize = sizeof(RingWriter),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_BASETYPE,
    .tp_new = writer_new,
    .tp_init = (initproc)writer_init,
    .tp_dealloc = (destructor)writer_dealloc,
    .tp_methods = writer_methods,
    .tp_members = writer_members,
    .tp_getset = writer_getset,
};

/* ----------------------------------------------------------------------------- reader */
typedef struct {
    PyObject_HEAD
    unsigned char *map;      /* kept until dealloc: a waker may be reading it */
    size_t size;
    uint32_t depth, slot_bytes;  /* our copy, checked once: the ring's words may change */
    uint64_t next;           /* the next frame we take: our own count */
    int doorbell;            /* our dup of the writer's eventfd */
    int closed;
    uint64_t lost;           /* frames overwritten (keep-last) or garbled before we took them */
    uint32_t writer_pid;
    uint32_t keep;           /* keep-last: at most this many of the newest frames are taken */
    pid_t pid;               /* the process that attached it: a forked child's copy says nothing */
} RingReader;

static PyObject *reader_new(PyTypeObject *type, PyObject *args, PyObject *kwds) {
    RingReader *self = (RingReader *)type->tp_alloc(type, 0);
    if (self != NULL)
        self->doorbell = -1;
    return (PyObject *)self;
}

/* RingReader(memfd, doorbell, depth, slot_bytes, keep=depth): check and map a ring a writer
 * handed over. The fds stay the caller's (to close); the doorbell is duplicated. */
static int reader_init(RingReader *self, PyObject *args, PyObject *kwds) {
    static char *kwlist[] = {"memfd", "doorbell", "depth", "slot_bytes", "keep", NULL};
    int memfd, bell;
    unsigned int depth, slot_bytes, keep = 0;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "iiII|I", kwlist, &memfd, &bell, &depth,
                                     &slot_bytes, &keep))
        return -1;
    if (self->map != NULL) {
        PyErr_SetString(PyExc_RuntimeError, "RingReader initialized twice");
        return -1;
    }
    if (!ring_geometry_ok(depth, slot_bytes)) {
        ring_error("a lane ring of %u slots of %u bytes", depth, slot_bytes);
        return -1;
    }
    size_t size = ring_file_size(depth, slot_bytes);
    int seals = fcntl(memfd, F_GET_SEALS);
    if (seals < 0) {
        ring_error("the lane ring is not a sealable memfd");
        return -1;
    }
    if ((seals & RING_SEALS) != RING_SEALS) {
        ring_error("the lane ring is not sealed against resizing (seals %#x)", seals);
        return -1;
    }
    struct stat st;
    if (fstat(memfd, &st) != 0 || (size_t)st.st_size != size) {
        ring_error("the lane ring is %lld bytes, not %zu", (long long)st.st_size, size);
        return -1;
    }
    struct stat bs;
    if (fstat(bell, &bs) != 0) {
        ring_oserror("the lane doorbell");
        return -1;
    }
    void *map = mmap(NULL, size, PROT_READ | PROT_WRITE, MAP_SHARED, memfd, 0);
    if (map == MAP_FAILED) {
        ring_oserror("cannot map the lane ring");
        return -1;
    }
    if (!ring_header_matches((ring_header *)map, depth, slot_bytes)) {
        munmap(map, size);
        ring_error("the lane ring's header does not match its hello");
        return -1;
    }
    int dup_bell = fcntl(bell, F_DUPFD_CLOEXEC, 3);
    if (dup_bell < 0) {
        ring_oserror("cannot keep the lane doorbell");
        munmap(map, size);
        return -1;
    }
    /* Our copy never blocks a read, whatever the writer made it */
    int flags = fcntl(dup_bell, F_GETFL);
    if (flags >= 0)
        fcntl(dup_bell, F_SETFL, flags | O_NONBLOCK);
    self->map = map;
    self->size = size;
    self->depth = depth;
    self->slot_bytes = slot_bytes;
    self->next = 0;
    self->doorbell = dup_bell;
    self->writer_pid = ((ring_header *)map)->writer_pid;
    self->keep = keep == 0 || keep > depth ? depth : keep;
    self->pid = this_pid;
    return 0;
}

static void reader_dealloc(RingReader *self) {
    if (self->map != NULL) {
        if (!self->closed && self->pid == this_pid)
            __atomic_store_n(&((ring_header *)self->map)->reader_closed, 1, __ATOMIC_SEQ_CST);
        munmap(self->map, self->size);
        self->map = NULL;
    }
    if (self->doorbell >= 0)
        close(self->doorbell);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* Is a frame waiting (the writer's tail past our count)? Safe without the GIL. */
static inline int reader_pending(RingReader *self) {
    if (self->closed || self->map == NULL)
        return 0;
    uint64_t tail = __atomic_load_n(&((ring_header *)self->map)->tail, __ATOMIC_ACQUIRE);
    return tail > self->next;
}

/* The next frame as bytes, NULL with no error when there is none. */
static PyObject *reader_take_one(RingReader *self) {
    if (self->closed || self->map == NULL)
        return NULL;
    ring_header *h = (ring_header *)self->map;
    uint32_t room = self->slot_bytes - RING_SLOT_HEAD;
    for (uint32_t tries = 0; tries <= self->depth; tries++) {
        uint64_t tail = __atomic_load_n(&h->tail, __ATOMIC_ACQUIRE);
        if (tail <= self->next)
            return NULL;  /* nothing new (or a tail that went back: a broken writer) */
        if (tail - self->next > self->keep) {  /* behind by more than we keep: the newest */
            self->lost += tail - self->next - self->keep;
            self->next = tail - self->keep;
        }
        uint64_t n = self->next;
        ring_slot *slot = ring_slot_at(self->map, self->depth, self->slot_bytes, n);
        uint64_t stamp = __atomic_load_n(&slot->stamp, __ATOMIC_ACQUIRE);
        uint64_t expected = 2 * n + 2;
        if (stamp != expected) {
            /* Overwritten since, or garbage: skip it. (A frame still being written behind a
             * tail that passed it is garbage too: a writer publishes the tail after the stamp,
             * so only a broken one shows it, and waiting for it would spin the waker.) */
            self->next = n + 1;
            self->lost++;
            continue;
        }
        uint32_t length = __atomic_load_n(&slot->length, __ATOMIC_RELAXED);
        if (length > room) {
            self->next = n + 1;
            self->lost++;
            continue;
        }
        PyObject *frame = PyBytes_FromStringAndSize(NULL, (Py_ssize_t)length);
        if (frame == NULL)
            return NULL;
        memcpy(PyBytes_AS_STRING(frame), slot->data, length);
        __atomic_thread_fence(__ATOMIC_ACQUIRE);
        if (__atomic_load_n(&slot->stamp, __ATOMIC_RELAXED) != stamp) {
            Py_DECREF(frame);  /* overwritten while we copied it */
            self->next = n + 1;
            self->lost++;
            continue;
        }
        self->next = n + 1;
        __atomic_store_n(&h->head, self->next, __ATOMIC_RELAXED);
        return frame;
    }
    return NULL;
}

static PyObject *reader_take(RingReader *self, PyObject *unused) {
    PyObject *frame = reader_take_one(self);
    if (frame == NULL && !PyErr_Occurred())
        Py_RETURN_NONE;
    return frame;
}

static PyObject *reader_close(RingReader *self, PyObject *unused) {
    /* The mapping and the doorbell stay until the object is gone (a waker may hold it). */
    if (!self->closed && self->map != NULL && self->pid == this_pid)
        __atomic_store_n(&((ring_header *)self->map)->reader_closed, 1, __ATOMIC_SEQ_CST);
    self->closed = 1;
    Py_RETURN_NONE;
}

static PyObject *reader_get_pending(RingReader *self, void *closure) {
    return PyBool_FromLong(reader_pending(self));
}

static PyObject *reader_writer_closed(RingReader *self, void *closure) {
    if (self->map == NULL)
        Py_RETURN_TRUE;
    return PyBool_FromLong(__atomic_load_n(&((ring_header *)self->map)->writer_closed,
                                           __ATOMIC_RELAXED) != 0);
}

static PyMethodDef reader_methods[] = {
    {"take", (PyCFunction)reader_take, METH_NOARGS,
     "take() -> bytes | None: the oldest frame not taken yet (copied out), or None."},
    {"close", (PyCFunction)reader_close, METH_NOARGS,
     "Tell the writer this end is closed; take() returns None from now on."},
    {NULL}
};

static PyMemberDef reader_members[] = {
    {"doorbell", T_INT, offsetof(RingReader, doorbell), READONLY, "our copy of the eventfd"},
    {"depth", T_UINT, offsetof(RingReader, depth), READONLY, "slots"},
    {"keep", T_UINT, offsetof(RingReader, keep), READONLY, "keep-last depth"},
    {"taken", T_ULONGLONG, offsetof(RingReader, next), READONLY, "frames taken or skipped"},
    {"lost", T_ULONGLONG, offsetof(RingReader, lost), READONLY,
     "frames overwritten (keep-last) or garbled before they were taken"},
    {"writer_pid", T_UINT, offsetof(RingReader, writer_pid), READONLY, "as the ring says"},
    {NULL}
};

static PyGetSetDef reader_getset[] = {
    {"pending", (getter)reader_get_pending, NULL, "a frame waits", NULL},
    {"writer_closed", (getter)reader_writer_closed, NULL, "the writer closed its end", NULL},
    {NULL}
};

static PyTypeObject RingReaderType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "buffer_pubsub._ring.RingReader",
    .tp_doc = "RingReader(memfd, doorbell, depth, slot_bytes): the reading end of a lane ring "
              "a writer handed over (checked: sealed memfd, size, header).",
    .tp_basicsize = sizeof(RingReader),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = reader_new,
    .tp_init = (initproc)reader_init,
    .tp_dealloc = (destructor)reader_dealloc,
    .tp_methods = reader_methods,
    .tp_members = reader_members,
    .tp_getset = reader_getset,
};

/* ----------------------------------------------------------------------------- waker */
typedef struct {
    RingReader *ring;
    PyObject *callback;  /* callback(frame: bytes) */
    PyObject *label;     /* passed to on_error with the exception */
} waker_entry;

typedef struct {
    PyObject_HEAD
    int efd;                 /* atomic: notify() writes it while the waiter sleeps */
    int notifying;           /* atomic: notify() calls writing efd without the GIL */
    int sleeping;            /* atomic: the waiter is (about to be) in ppoll */
    int notified;            /* atomic */
    int in_wait;             /* a thread is inside wait(): the sets are not to change */
    double busy_poll_s;
    waker_entry *entries;
    Py_ssize_t nentries;
    int *fds;                /* other fds to watch, reported back by wait() */
    short *fd_events;
    Py_ssize_t nfds;
    struct pollfd *pfds;     /* efd, doorbells, fds */
    PyObject *on_error;
    PyObject *empty;         /* () : what wait() returns when no watched fd fired */
    uint64_t wakeups;        /* ppoll returns */
} Waker;

static void waker_close_efd(Waker *self);

static PyObject *waker_new(PyTypeObject *type, PyObject *args, PyObject *kwds) {
    Waker *self = (Waker *)type->tp_alloc(type, 0);
    if (self != NULL)
        self->efd = -1;
    return (PyObject *)self;
}

static int waker_init(Waker *self, PyObject *args, PyObject *kwds) {
    static char *kwlist[] = {"on_error", "busy_poll_s", NULL};
    PyObject *on_error = Py_None;
    double busy = 0.0;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "|Od", kwlist, &on_error, &busy))
        return -1;
    if (self->efd >= 0 || self->pfds != NULL) {  /* (closed: still its buffers) */
        PyErr_SetString(PyExc_RuntimeError, "Waker initialized twice");
        return -1;
    }
    self->efd = eventfd(0, EFD_CLOEXEC | EFD_NONBLOCK);
    if (self->efd < 0) {
        ring_oserror("eventfd");
        return -1;
    }
    self->pfds = PyMem_Calloc(1, sizeof(struct pollfd));
    self->empty = PyTuple_New(0);
    if (self->pfds == NULL || self->empty == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    self->pfds[0].fd = self->efd;
    self->pfds[0].events = POLLIN;
    Py_INCREF(on_error);
    self->on_error = on_error;
    self->busy_poll_s = busy > 0 ? busy : 0.0;
    return 0;
}

static void waker_clear_sets(Waker *self) {
    for (Py_ssize_t i = 0; i < self->nentries; i++) {
        Py_XDECREF(self->entries[i].ring);
        Py_XDECREF(self->entries[i].callback);
        Py_XDECREF(self->entries[i].label);
    }
    PyMem_Free(self->entries);
    PyMem_Free(self->fds);
    PyMem_Free(self->fd_events);
    self->entries = NULL;
    self->fds = NULL;
    self->fd_events = NULL;
    self->nentries = self->nfds = 0;
}

static void waker_dealloc(Waker *self) {
    waker_clear_sets(self);
    PyMem_Free(self->pfds);
    Py_XDECREF(self->on_error);
    Py_XDECREF(self->empty);
    waker_close_efd(self);  /* (no notify() runs: it holds a reference) */
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* watch(rings, fds): rings = [(RingReader, callback, label)], fds = [(fd, events)]. Only
 * between waits (the waiting thread applies changes). */
static PyObject *waker_watch(Waker *self, PyObject *args) {
    PyObject *rings, *fds;
    if (!PyArg_ParseTuple(args, "OO", &rings, &fds))
        return NULL;
    if (self->in_wait)
        return ring_error("the waker's sets change only between waits");
    if (self->efd < 0)
        return ring_error("the waker is closed");
    PyObject *rs = PySequence_Fast(rings, "rings must be a sequence");
    if (rs == NULL)
        return NULL;
    PyObject *fs = PySequence_Fast(fds, "fds must be a sequence");
    if (fs == NULL) {
        Py_DECREF(rs);
        return NULL;
    }
    Py_ssize_t nr = PySequence_Fast_GET_SIZE(rs), nf = PySequence_Fast_GET_SIZE(fs);
    waker_entry *entries = PyMem_Calloc(nr ? nr : 1, sizeof(waker_entry));
    int *fdv = PyMem_Calloc(nf ? nf : 1, sizeof(int));
    short *evv = PyMem_Calloc(nf ? nf : 1, sizeof(short));
    struct pollfd *pfds = PyMem_Calloc(1 + nr + nf, sizeof(struct pollfd));
    if (!entries || !fdv || !evv || !pfds) {
        PyErr_NoMemory();
        goto fail;
    }
    for (Py_ssize_t i = 0; i < nr; i++) {
        PyObject *item = PySequence_Fast_GET_ITEM(rs, i);
        PyObject *ring, *callback, *label;
        if (!PyArg_ParseTuple(item, "O!OO", &RingReaderType, &ring, &callback, &label))
            goto fail_entries;
        Py_INCREF(ring);
        Py_INCREF(callback);
        Py_INCREF(label);
        entries[i].ring = (RingReader *)ring;
        entries[i].callback = callback;
        entries[i].label = label;
    }
    for (Py_ssize_t i = 0; i < nf; i++) {
        PyObject *item = PySequence_Fast_GET_ITEM(fs, i);
        int fd, events;
        if (!PyArg_ParseTuple(item, "ii", &fd, &events))
            goto fail_entries;
        fdv[i] = fd;
        evv[i] = (short)events;
    }
    Py_DECREF(rs);
    Py_DECREF(fs);
    waker_clear_sets(self);
    PyMem_Free(self->pfds);
    self->entries = entries;
    self->nentries = nr;
    self->fds = fdv;
    self->fd_events = evv;
    self->nfds = nf;
    self->pfds = pfds;
    pfds[0].fd = self->efd;
    pfds[0].events = POLLIN;
    for (Py_ssize_t i = 0; i < nr; i++) {
        pfds[1 + i].fd = entries[i].ring->closed ? -1 : entries[i].ring->doorbell;
        pfds[1 + i].events = POLLIN;
    }
    for (Py_ssize_t i = 0; i < nf; i++) {
        pfds[1 + nr + i].fd = fdv[i];
        pfds[1 + nr + i].events = evv[i];
    }
    Py_RETURN_NONE;
fail_entries:
    for (Py_ssize_t i = 0; i < nr; i++) {
        Py_XDECREF(entries[i].ring);
        Py_XDECREF(entries[i].callback);
        Py_XDECREF(entries[i].label);
    }
fail:
    Py_DECREF(rs);
    Py_DECREF(fs);
    PyMem_Free(entries);
    PyMem_Free(fdv);
    PyMem_Free(evv);
    PyMem_Free(pfds);
    return NULL;
}

/* Deliver every waiting frame of every ring to its callback; how many. A callback that raises
 * goes to on_error(label, exception) and the frames behind it are still delivered. */
static Py_ssize_t waker_drain(Waker *self) {
    Py_ssize_t delivered = 0;
    for (Py_ssize_t i = 0; i < self->nentries; i++) {
        waker_entry *e = &self->entries[i];
        for (uint32_t k = 0; k <= e->ring->depth; k++) {  /* bounded: a fast writer cannot
                                                            * keep us here forever */
            PyObject *frame = reader_take_one(e->ring);
            if (frame == NULL) {
                if (PyErr_Occurred())
                    return -1;
                break;
            }
            delivered++;
            PyObject *result = PyObject_CallOneArg(e->callback, frame);
            Py_DECREF(frame);
            if (result != NULL) {
                Py_DECREF(result);
                continue;
            }
            if (PyErr_ExceptionMatches(PyExc_KeyboardInterrupt)
                    || PyErr_ExceptionMatches(PyExc_SystemExit))
                return -1;
            PyObject *type, *value, *tb;
            PyErr_Fetch(&type, &value, &tb);
            PyErr_NormalizeException(&type, &value, &tb);
            if (tb != NULL && value != NULL)
                PyException_SetTraceback(value, tb);
            if (self->on_error != Py_None && value != NULL) {
                PyObject *r = PyObject_CallFunctionObjArgs(self->on_error, e->label, value,
                                                           NULL);
                if (r == NULL)
                    PyErr_WriteUnraisable(self->on_error);
                Py_XDECREF(r);
            }
            Py_XDECREF(type);
            Py_XDECREF(value);
            Py_XDECREF(tb);
        }
    }
    return delivered;
}

static int waker_any_pending(Waker *self) {
    for (Py_ssize_t i = 0; i < self->nentries; i++)
        if (reader_pending(self->entries[i].ring))
            return 1;
    return 0;
}

static void waker_set_waiting(Waker *self, uint32_t value) {
    for (Py_ssize_t i = 0; i < self->nentries; i++) {
        RingReader *r = self->entries[i].ring;
        if (!r->closed && r->map != NULL)
            __atomic_store_n(&((ring_header *)r->map)->waiting, value, __ATOMIC_SEQ_CST);
    }
}

static double now_s(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + ts.tv_nsec * 1e-9;
}

/* wait(timeout=None) -> tuple of (fd, revents) of the watched fds that fired.
 * Delivers waiting frames first; sleeps only when there were none and no notify() came. */
static PyObject *waker_wait(Waker *self, PyObject *const *args, Py_ssize_t nargs) {
    double timeout = -1.0;  /* < 0: no limit */
    if (nargs > 1) {
        PyErr_SetString(PyExc_TypeError, "wait(timeout=None)");
        return NULL;
    }
    if (nargs == 1 && args[0] != Py_None) {
        timeout = PyFloat_AsDouble(args[0]);
        if (timeout == -1.0 && PyErr_Occurred())
            return NULL;
        if (!(timeout > 0))
            timeout = 0.0;  /* negative, zero and NaN: do not sleep */
        else if (timeout > 1e9)
            timeout = -1.0;
    }
    if (self->efd < 0)
        return ring_error("the waker is closed");
    if (self->in_wait)
        return ring_error("one thread waits on a waker at a time");
    self->in_wait = 1;
    PyObject *result = NULL;
    int notified = __atomic_exchange_n(&self->notified, 0, __ATOMIC_SEQ_CST);
    Py_ssize_t delivered = waker_drain(self);
    if (delivered < 0)
        goto done;
    if (notified || delivered > 0 || timeout == 0.0) {
        result = Py_NewRef(self->empty);
        goto done;
    }
    /* Sleep: announce it, then look once more (Dekker with notify() and the writers). */
    waker_set_waiting(self, 1);
    __atomic_store_n(&self->sleeping, 1, __ATOMIC_SEQ_CST);
    int rc = 0, err = 0;
    Py_ssize_t npfds = 1 + self->nentries + self->nfds;
    for (Py_ssize_t i = 0; i < npfds; i++)
        self->pfds[i].revents = 0;
    if (!__atomic_load_n(&self->notified, __ATOMIC_SEQ_CST) && !waker_any_pending(self)) {
        Py_BEGIN_ALLOW_THREADS
        double start = now_s();
        if (self->busy_poll_s > 0) {  /* spin, then block */
            double spin = timeout < 0 || self->busy_poll_s < timeout ? self->busy_poll_s : timeout;
            while (now_s() - start < spin) {
                if (__atomic_load_n(&self->notified, __ATOMIC_ACQUIRE) || waker_any_pending(self)) {
                    rc = -2;  /* found while spinning */
                    break;
                }
            }
        }
        if (rc != -2) {
            struct timespec ts, *tsp = NULL;
            if (timeout >= 0) {
                double left = timeout - (now_s() - start);
                if (left < 0)
                    left = 0;
                ts.tv_sec = (time_t)left;
                ts.tv_nsec = (long)((left - (double)ts.tv_sec) * 1e9);
                tsp = &ts;
            }
            rc = ppoll(self->pfds, (nfds_t)npfds, tsp, NULL);
            err = errno;
        }
        Py_END_ALLOW_THREADS
        self->wakeups++;
    }
    __atomic_store_n(&self->sleeping, 0, __ATOMIC_SEQ_CST);
    waker_set_waiting(self, 0);
    /* Reset the eventfds that fired (a count left behind only makes a later wait return early) */
    uint64_t count;
    for (Py_ssize_t i = 0; i < 1 + self->nentries; i++) {
        if (self->pfds[i].revents & POLLIN) {
            ssize_t ignored = read(self->pfds[i].fd, &count, sizeof count);
            (void)ignored;
        }
    }
    __atomic_store_n(&self->notified, 0, __ATOMIC_SEQ_CST);
    if (rc == -1 && err == EINTR && PyErr_CheckSignals() != 0)
        goto done;  /* KeyboardInterrupt and friends */
    if (waker_drain(self) < 0)
        goto done;
    if (rc > 0 && self->nfds > 0) {
        Py_ssize_t fired = 0;
        for (Py_ssize_t i = 0; i < self->nfds; i++)
            fired += self->pfds[1 + self->nentries + i].revents != 0;
        if (fired) {
            result = PyTuple_New(fired);
            if (result == NULL)
                goto done;
            Py_ssize_t k = 0;
            for (Py_ssize_t i = 0; i < self->nfds; i++) {
                struct pollfd *p = &self->pfds[1 + self->nentries + i];
                if (p->revents) {
                    PyObject *pair = Py_BuildValue("(ii)", p->fd, (int)p->revents);
                    if (pair == NULL) {
                        Py_CLEAR(result);
                        goto done;
                    }
                    PyTuple_SET_ITEM(result, k++, pair);
                }
            }
            goto done;
        }
    }
    result = Py_NewRef(self->empty);
done:
    self->in_wait = 0;
    return result;
}

/* notify(): wake the waiter (or make its next wait return at once). Any thread. */
static PyObject *waker_notify(Waker *self, PyObject *unused) {
    __atomic_store_n(&self->notified, 1, __ATOMIC_SEQ_CST);
    if (!__atomic_load_n(&self->sleeping, __ATOMIC_SEQ_CST))
        Py_RETURN_NONE;
    /* The write runs without the GIL: the waiter it wakes takes the GIL at once (an in-process
     * subscription's callback starts while this thread returns from publish()) instead of
     * waking only to wait for it. close() waits for such a write before it closes the fd
     * (counted in `notifying`, read after efd: whichever of the two comes second sees the
     * other's store). */
    __atomic_add_fetch(&self->notifying, 1, __ATOMIC_SEQ_CST);
    int fd = __atomic_load_n(&self->efd, __ATOMIC_SEQ_CST);
    if (fd < 0) {
        __atomic_sub_fetch(&self->notifying, 1, __ATOMIC_SEQ_CST);
        Py_RETURN_NONE;
    }
    Py_BEGIN_ALLOW_THREADS
    uint64_t one = 1;
    ssize_t ignored = write(fd, &one, sizeof one);
    (void)ignored;
    __atomic_sub_fetch(&self->notifying, 1, __ATOMIC_SEQ_CST);  /* before the GIL: see close */
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

/* Close the eventfd once no notify() is writing it (each such write ends without needing the
 * GIL, which the caller holds). */
static void waker_close_efd(Waker *self) {
    int fd = __atomic_exchange_n(&self->efd, -1, __ATOMIC_SEQ_CST);
    if (fd < 0)
        return;
    while (__atomic_load_n(&self->notifying, __ATOMIC_SEQ_CST))
        sched_yield();
    close(fd);
}

static PyObject *waker_close(Waker *self, PyObject *unused) {
    if (self->in_wait)
        return ring_error("close the waker from its waiting thread, or once it returned");
    waker_clear_sets(self);
    waker_close_efd(self);
    Py_RETURN_NONE;
}

/* In a fork's child: the threads inside wait() and notify() at the fork were the parent's, and
 * none of them is here to leave (close would refuse, or wait for them, for ever). */
static PyObject *waker_after_fork(Waker *self, PyObject *unused) {
    self->in_wait = 0;
    __atomic_store_n(&self->sleeping, 0, __ATOMIC_SEQ_CST);
    __atomic_store_n(&self->notifying, 0, __ATOMIC_SEQ_CST);
    Py_RETURN_NONE;
}

static PyObject *waker_get_notified(Waker *self, void *closure) {
    return PyBool_FromLong(__atomic_load_n(&self->notified, __ATOMIC_SEQ_CST));
}

static PyObject *waker_get_pending(Waker *self, void *closure) {
    return PyBool_FromLong(waker_any_pending(self));
}

static PyMethodDef waker_methods[] = {
    {"wait", (PyCFunction)(void (*)(void))waker_wait, METH_FASTCALL,
     "wait(timeout=None) -> tuple[(fd, revents)]: deliver waiting frames; sleep (GIL released) "
     "until notify(), a doorbell or a watched fd when there were none; deliver again."},
    {"notify", (PyCFunction)waker_notify, METH_NOARGS, "Wake the waiter (any thread)."},
    {"watch", (PyCFunction)waker_watch, METH_VARARGS,
     "watch(rings, fds): the rings [(RingReader, callback, label)] and fds [(fd, events)] to "
     "watch (between waits only)."},
    {"close", (PyCFunction)waker_close, METH_NOARGS, "Release the eventfd and the sets."},
    {"after_fork", (PyCFunction)waker_after_fork, METH_NOARGS,
     "In a fork's child: forget the parent's threads inside wait() and notify()."},
    {NULL}
};

static PyMemberDef waker_members[] = {
    {"busy_poll_s", T_DOUBLE, offsetof(Waker, busy_poll_s), 0,
     "seconds each wait spins (GIL released, a core at 100%) before it blocks"},
    {"wakeups", T_ULONGLONG, offsetof(Waker, wakeups), READONLY, "times the waiter slept"},
    {"fd", T_INT, offsetof(Waker, efd), READONLY, "the notify eventfd (-1: closed)"},
    {NULL}
};

static PyGetSetDef waker_getset[] = {
    {"notified", (getter)waker_get_notified, NULL, "a notify() is pending", NULL},
    {"pending", (getter)waker_get_pending, NULL, "a ring has a frame waiting", NULL},
    {NULL}
};

static PyTypeObject WakerType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "buffer_pubsub._ring.Waker",
    .tp_doc = "Waker(on_error=None, busy_poll_s=0.0): one thread's wait on lane rings, "
              "watched fds and notify().",
    .tp_basicsize = sizeof(Waker),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_BASETYPE,
    .tp_new = waker_new,
    .tp_init = (initproc)waker_init,
    .tp_dealloc = (destructor)waker_dealloc,
    .tp_methods = waker_methods,
    .tp_members = waker_members,
    .tp_getset = waker_getset,
};

/* ----------------------------------------------------------------------------- module */
static PyObject *set_error_class(PyObject *module, PyObject *cls) {
    if (!PyType_Check(cls) || !PyType_IsSubtype((PyTypeObject *)cls,
                                                (PyTypeObject *)PyExc_Exception)) {
        PyErr_SetString(PyExc_TypeError, "an exception class");
        return NULL;
    }
    Py_INCREF(cls);
    Py_XSETREF(RingError, cls);
    Py_RETURN_NONE;
}

static PyMethodDef module_methods[] = {
    {"set_error_class", set_error_class, METH_O,
     "The exception class the ring raises (buffer_pubsub.fast_lane.LaneError)."},
    {NULL}
};

static struct PyModuleDef ring_module = {
    PyModuleDef_HEAD_INIT, "buffer_pubsub._ring",
    "The same-host lane's native core: memfd rings with an eventfd doorbell, and the waker.",
    -1, module_methods,
};

PyMODINIT_FUNC PyInit__ring(void) {
    refresh_pid();
    if (pthread_atfork(NULL, NULL, refresh_pid) != 0) {
        PyErr_SetString(PyExc_RuntimeError, "pthread_atfork failed");
        return NULL;
    }
    if (PyType_Ready(&RingWriterType) < 0 || PyType_Ready(&RingReaderType) < 0
            || PyType_Ready(&WakerType) < 0)
        return NULL;
    PyObject *m = PyModule_Create(&ring_module);
    if (m == NULL)
        return NULL;
    if (PyModule_AddObjectRef(m, "RingWriter", (PyObject *)&RingWriterType) < 0
            || PyModule_AddObjectRef(m, "RingReader", (PyObject *)&RingReaderType) < 0
            || PyModule_AddObjectRef(m, "Waker", (PyObject *)&WakerType) < 0
            || PyModule_AddIntConstant(m, "DEFAULT_SLOT", RING_DEFAULT_SLOT) < 0
            || PyModule_AddIntConstant(m, "SLOT_HEAD", RING_SLOT_HEAD) < 0
            || PyModule_AddIntConstant(m, "MAX_DEPTH", RING_MAX_DEPTH) < 0
            || PyModule_AddIntConstant(m, "HEADER_BYTES", RING_HEADER_BYTES) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
