/* buffer_pubsub._streams: the per-message checks of an arrival, in C.
 *
 * - parse_attachment / split_frame: the 33-byte attachment rmw_zenoh puts beside every sample
 *   (int64 sequence, int64 source timestamp, the gid's length byte 0x10, 16 bytes of gid, all
 *   little-endian), alone or at the head of a lane frame;
 * - Streams: what a subscription learns from the attachments it receives (gaps, late messages,
 *   second copies), the rules of buffer_pubsub.subscription's module docstring:
 *
 *   Sequence numbers are judged per stream and publisher. A publisher that numbers the stream on
 *   its own ("exact": ours, or any publisher on the base key) steps by one, so a step of n > 1 is
 *   n - 1 messages lost. rmw_zenoh's buffer-aware publishers number every put, so on one stream
 *   their numbers advance by their fan-out: that stride is learned from the steps themselves (a
 *   step seen twice running is the stride; a whole multiple of it is loss, judged one message
 *   late). A step back within LOST_WINDOW is a late message (a route switch of ours let a later
 *   one overtake it), unless the publisher "restarts": another implementation's counter only
 *   goes back when it started again (rmw_zenoh never drops such a message), so it resynchronizes
 *   there, as any larger jump does.
 *   One of our publishers serving a subscription by two routes at once sends the same message
 *   twice, with the same source timestamp (strictly increasing per publisher): the second copy
 *   is recognized among the last RECENT_STAMPS stamps of that publisher.
 *
 * Both tables forget their oldest entry past MAX_TRACKED. Not thread-safe: the subscription
 * calls under its lock (and the GIL). One C call per arrival; no Python frame.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <endian.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>

#define ATTACHMENT_SIZE 33
#define GID_SIZE 16
#define GID_LENGTH_PREFIX 0x10
#define LOST_WINDOW ((int64_t)1 << 16)
#define MAX_TRACKED 1024
#define RECENT_STAMPS 256

static PyObject *new_attachment;  /* wire.new_attachment: (seq, stamp, gid) -> Attachment */
static PyObject *wire_error;      /* buffer_pubsub.errors.WireFormatError */

/* ----------------------------------------------------------------------------- attachment */
static PyObject *attachment_from(const unsigned char *data) {
    if (new_attachment == NULL || wire_error == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "buffer_pubsub._streams is not configured");
        return NULL;
    }
    if (data[16] != GID_LENGTH_PREFIX) {
        PyErr_Format(wire_error, "attachment gid length prefix is 0x%x, not 0x10", data[16]);
        return NULL;
    }
    uint64_t sequence, stamp;
    memcpy(&sequence, data, 8);
    memcpy(&stamp, data + 8, 8);
    PyObject *fields = Py_BuildValue("(LLy#)", (long long)(int64_t)le64toh(sequence),
                                     (long long)(int64_t)le64toh(stamp),
                                     (const char *)data + 17, (Py_ssize_t)GID_SIZE);
    if (fields == NULL)
        return NULL;
    PyObject *args[1] = {fields};
    PyObject *attachment = PyObject_Vectorcall(new_attachment, args, 1, NULL);
    Py_DECREF(fields);
    return attachment;
}

/* WireFormatError: no attachment, or one too short (`got`: what came instead). */
static PyObject *too_short(const char *got) {
    if (wire_error == NULL)
        PyErr_SetString(PyExc_RuntimeError, "buffer_pubsub._streams is not configured");
    else
        PyErr_Format(wire_error, "attachment must be %d bytes, got %s", ATTACHMENT_SIZE, got);
    return NULL;
}

static PyObject *too_short_by(Py_ssize_t size) {
    char got[32];
    snprintf(got, sizeof got, "%zd", size);
    return too_short(got);
}

static PyObject *parse_attachment(PyObject *module, PyObject *data) {
    if (data == Py_None)
        return too_short("None");
    Py_buffer view;
    if (PyObject_GetBuffer(data, &view, PyBUF_SIMPLE) < 0)
        return NULL;
    PyObject *result = NULL;
    /* As rmw_zenoh's deserializer: the fields it knows, and whatever follows them ignored. */
    if (view.len < ATTACHMENT_SIZE) {
        too_short_by(view.len);
    } else {
        result = attachment_from(view.buf);
    }
    PyBuffer_Release(&view);
    return result;
}

/* A lane frame: the attachment, then the CDR payload (a memoryview of the frame's tail). */
static PyObject *split_frame(PyObject *module, PyObject *data) {
    if (!PyBytes_Check(data)) {
        PyErr_Format(PyExc_TypeError, "a lane frame is bytes, not %.100s", Py_TYPE(data)->tp_name);
        return NULL;
    }
    Py_ssize_t size = PyBytes_GET_SIZE(data);
    if (size < ATTACHMENT_SIZE)
        return too_short_by(size);
    PyObject *attachment = attachment_from((const unsigned char *)PyBytes_AS_STRING(data));
    if (attachment == NULL)
        return NULL;
    /* A read-only view of the bytes object's tail (it keeps the bytes alive). */
    PyObject *whole = PyMemoryView_FromObject(data);
    if (whole == NULL) {
        Py_DECREF(attachment);
        return NULL;
    }
    PyObject *start = PyLong_FromSsize_t(ATTACHMENT_SIZE);
    PyObject *slice = start ? PySlice_New(start, NULL, NULL) : NULL;
    Py_XDECREF(start);
    PyObject *payload = slice ? PyObject_GetItem(whole, slice) : NULL;
    Py_XDECREF(slice);
    Py_DECREF(whole);
    if (payload == NULL) {
        Py_DECREF(attachment);
        return NULL;
    }
    PyObject *pair = PyTuple_Pack(2, attachment, payload);
    Py_DECREF(attachment);
    Py_DECREF(payload);
    return pair;
}

/* pack_attachment(sequence, stamp, gid) -> the 33 bytes (what every put and lane frame carries). */
static PyObject *pack_attachment(PyObject *module, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "pack_attachment(sequence, stamp, gid) takes 3 arguments");
        return NULL;
    }
    long long sequence = PyLong_AsLongLong(args[0]);
    if (sequence == -1 && PyErr_Occurred())
        return NULL;
    long long stamp = PyLong_AsLongLong(args[1]);
    if (stamp == -1 && PyErr_Occurred())
        return NULL;
    if (!PyBytes_Check(args[2]) || PyBytes_GET_SIZE(args[2]) != GID_SIZE) {
        PyErr_SetString(PyExc_ValueError, "a gid is 16 bytes");
        return NULL;
    }
    PyObject *out = PyBytes_FromStringAndSize(NULL, ATTACHMENT_SIZE);
    if (out == NULL)
        return NULL;
    unsigned char *data = (unsigned char *)PyBytes_AS_STRING(out);
    uint64_t word = htole64((uint64_t)sequence);
    memcpy(data, &word, 8);
    word = htole64((uint64_t)stamp);
    memcpy(data + 8, &word, 8);
    data[16] = GID_LENGTH_PREFIX;
    memcpy(data + 17, PyBytes_AS_STRING(args[2]), GID_SIZE);
    return out;
}

/* ----------------------------------------------------------------------------- per-key state */
/* A stream of one publisher: its last number and what its steps taught (its stride). */
typedef struct {
    PyObject_HEAD
    int64_t last;
    int64_t stride;    /* 0: not learned yet */
    int64_t odd_step;  /* a step that differed from the stride, judged at the next arrival */
    int64_t odd_lost;  /* what it means if the stride holds */
} Channel;

static PyTypeObject ChannelType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "buffer_pubsub._streams._Channel",
    .tp_basicsize = sizeof(Channel),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "One stream of one publisher (internal).",
};

static void channel_reset(Channel *channel, int64_t sequence) {
    channel->last = sequence;
    channel->stride = channel->odd_step = channel->odd_lost = 0;
}

/* The last RECENT_STAMPS distinct source timestamps of one publisher (a ring). */
typedef struct {
    PyObject_HEAD
    int64_t stamps[RECENT_STAMPS];
    int count;
    int next;
} Recent;

static PyTypeObject RecentType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "buffer_pubsub._streams._Recent",
    .tp_basicsize = sizeof(Recent),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "The recent source timestamps of one publisher (internal).",
};

/* Forget the oldest entry of `table` (dicts keep insertion order). */
static int forget_oldest(PyObject *table) {
    Py_ssize_t pos = 0;
    PyObject *key, *value;
    if (!PyDict_Next(table, &pos, &key, &value))
        return 0;
    Py_INCREF(key);
    int result = PyDict_DelItem(table, key);
    Py_DECREF(key);
    return result;
}

/* ----------------------------------------------------------------------------- verdicts */
/* What one arrival says: lost before it, late (older than one already seen), jump (resync). */
typedef struct {
    int64_t lost;
    int late;
    int jump;
} Verdict;

static int in_order(const Verdict *v) {
    return v->lost == 0 && !v->late && !v->jump;
}

static void judge_stride(Channel *state, int64_t step, Verdict *v) {
    int64_t lost = 0;
    if (state->odd_step) {  /* the previous step differed from the stride: judged now */
        if (step == state->odd_step) {  /* it repeats: the publisher's fan-out changed */
            state->stride = step;
            state->odd_step = state->odd_lost = 0;
            return;
        }
        lost = state->odd_lost;
        state->odd_step = state->odd_lost = 0;
    }
    if (state->stride == 0) {
        state->stride = step;
    } else if (step != state->stride) {
        state->odd_step = step;
        state->odd_lost = step % state->stride == 0 ? step / state->stride - 1 : 0;
    }
    v->lost = lost;
}

typedef struct {
    PyObject_HEAD
    PyObject *channels;  /* (stream, gid) -> Channel */
    PyObject *recent;    /* gid -> Recent */
} Streams;

static int track(Streams *self, PyObject *stream, PyObject *gid, int64_t sequence, int exact,
                 int from_one, int restarts, Verdict *v) {
    memset(v, 0, sizeof *v);
    PyObject *key = PyTuple_Pack(2, stream, gid);
    if (key == NULL)
        return -1;
    Channel *state = (Channel *)PyDict_GetItemWithError(self->channels, key);
    if (state == NULL) {
        if (PyErr_Occurred() || (PyDict_GET_SIZE(self->channels) >= MAX_TRACKED
                                 && forget_oldest(self->channels) < 0)) {
            Py_DECREF(key);
            return -1;
        }
        state = PyObject_New(Channel, &ChannelType);
        if (state == NULL) {
            Py_DECREF(key);
            return -1;
        }
        channel_reset(state, sequence);
        int failed = PyDict_SetItem(self->channels, key, (PyObject *)state);
        Py_DECREF(state);
        Py_DECREF(key);
        if (failed)
            return -1;
        if (from_one && exact && 1 < sequence && sequence <= LOST_WINDOW)
            v->lost = sequence - 1;
        return 0;
    }
    Py_DECREF(key);
    int64_t step;
    if (__builtin_sub_overflow(sequence, state->last, &step)) {
        channel_reset(state, sequence);  /* beyond any window either way */
        v->jump = 1;
        return 0;
    }
    if (step <= 0) {
        if (step > -LOST_WINDOW && !restarts) {
            v->late = 1;
            return 0;
        }
        channel_reset(state, sequence);  /* a restarted counter */
        v->jump = 1;
        return 0;
    }
    if (step > LOST_WINDOW) {
        channel_reset(state, sequence);
        v->jump = 1;
        return 0;
    }
    state->last = sequence;
    if (exact)
        v->lost = step - 1;
    else
        judge_stride(state, step, v);
    return 0;
}

/* 1: `stamp` of `gid` arrived already; 0: it is new (and remembered); -1: an error. */
static int seen_before(Streams *self, PyObject *gid, int64_t stamp) {
    Recent *entry = (Recent *)PyDict_GetItemWithError(self->recent, gid);
    if (entry == NULL) {
        if (PyErr_Occurred() || (PyDict_GET_SIZE(self->recent) >= MAX_TRACKED
                                 && forget_oldest(self->recent) < 0))
            return -1;
        entry = PyObject_New(Recent, &RecentType);
        if (entry == NULL)
            return -1;
        entry->count = entry->next = 0;
        int failed = PyDict_SetItem(self->recent, gid, (PyObject *)entry);
        Py_DECREF(entry);
        if (failed)
            return -1;
    }
    for (int i = 0; i < entry->count; i++)
        if (entry->stamps[i] == stamp)
            return 1;
    entry->stamps[entry->next] = stamp;
    entry->next = (entry->next + 1) % RECENT_STAMPS;
    if (entry->count < RECENT_STAMPS)
        entry->count++;
    return 0;
}

static PyObject *verdict_tuple(int duplicate, const Verdict *v) {
    return Py_BuildValue("(OLOO)", duplicate ? Py_True : Py_False, (long long)v->lost,
                         v->late ? Py_True : Py_False, v->jump ? Py_True : Py_False);
}

static int check_gid(PyObject *gid) {
    if (!PyBytes_Check(gid)) {
        PyErr_Format(PyExc_TypeError, "a gid is bytes, not %.100s", Py_TYPE(gid)->tp_name);
        return -1;
    }
    return 0;
}

static int check_stream(PyObject *stream) {
    if (!PyUnicode_Check(stream)) {
        PyErr_Format(PyExc_TypeError, "a stream is named by a str, not %.100s",
                     Py_TYPE(stream)->tp_name);
        return -1;
    }
    return 0;
}

static int int64_arg(PyObject *value, const char *what, int64_t *out) {
    if (!PyLong_Check(value)) {
        PyErr_Format(PyExc_TypeError, "%s is an int, not %.100s", what, Py_TYPE(value)->tp_name);
        return -1;
    }
    long long number = PyLong_AsLongLong(value);
    if (number == -1 && PyErr_Occurred())
        return -1;  /* OverflowError: the wire carries int64 */
    *out = number;
    return 0;
}

/* ----------------------------------------------------------------------------- Streams methods */
static PyObject *streams_new(PyTypeObject *type, PyObject *args, PyObject *kwargs) {
    if (PyTuple_GET_SIZE(args) || (kwargs != NULL && PyDict_GET_SIZE(kwargs))) {
        PyErr_SetString(PyExc_TypeError, "Streams() takes no arguments");
        return NULL;
    }
    Streams *self = (Streams *)type->tp_alloc(type, 0);
    if (self == NULL)
        return NULL;
    self->channels = PyDict_New();
    self->recent = PyDict_New();
    if (self->channels == NULL || self->recent == NULL) {
        Py_DECREF(self);
        return NULL;
    }
    return (PyObject *)self;
}

static void streams_dealloc(Streams *self) {
    Py_XDECREF(self->channels);
    Py_XDECREF(self->recent);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* track(stream, gid, sequence, exact, from_one=False, restarts=False) */
static PyObject *streams_track(Streams *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs < 4 || nargs > 6) {
        PyErr_SetString(PyExc_TypeError,
                        "track(stream, gid, sequence, exact, from_one=False, restarts=False) "
                        "takes 4 to 6 arguments");
        return NULL;
    }
    int64_t sequence;
    if (check_stream(args[0]) < 0 || check_gid(args[1]) < 0
            || int64_arg(args[2], "a sequence number", &sequence) < 0)
        return NULL;
    int exact, from_one = 0, restarts = 0;
    if ((exact = PyObject_IsTrue(args[3])) < 0
            || (nargs >= 5 && (from_one = PyObject_IsTrue(args[4])) < 0)
            || (nargs == 6 && (restarts = PyObject_IsTrue(args[5])) < 0))
        return NULL;
    Verdict v;
    if (track(self, args[0], args[1], sequence, exact, from_one, restarts, &v) < 0)
        return NULL;
    if (in_order(&v))
        Py_RETURN_NONE;
    return verdict_tuple(0, &v);
}

/* admit(stream, gid, sequence, stamp, exact, from_one, restarts): stamp None: no duplicate
 * check */
static PyObject *streams_admit(Streams *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 7) {
        PyErr_SetString(PyExc_TypeError, "admit(stream, gid, sequence, stamp, exact, from_one, "
                                         "restarts) takes 7 arguments");
        return NULL;
    }
    int64_t sequence, stamp = 0;
    if (check_stream(args[0]) < 0 || check_gid(args[1]) < 0
            || int64_arg(args[2], "a sequence number", &sequence) < 0
            || (args[3] != Py_None && int64_arg(args[3], "a source timestamp", &stamp) < 0))
        return NULL;
    int exact, from_one, restarts;
    if ((exact = PyObject_IsTrue(args[4])) < 0 || (from_one = PyObject_IsTrue(args[5])) < 0
            || (restarts = PyObject_IsTrue(args[6])) < 0)
        return NULL;
    int duplicate = 0;
    if (args[3] != Py_None) {
        duplicate = seen_before(self, args[1], stamp);
        if (duplicate < 0)
            return NULL;
    }
    Verdict v;
    if (track(self, args[0], args[1], sequence, exact, from_one, restarts, &v) < 0)
        return NULL;
    if (!duplicate && in_order(&v))
        Py_RETURN_NONE;
    return verdict_tuple(duplicate, &v);
}

static PyObject *streams_seen_before(Streams *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "seen_before(gid, stamp) takes 2 arguments");
        return NULL;
    }
    int64_t stamp;
    if (check_gid(args[0]) < 0 || int64_arg(args[1], "a source timestamp", &stamp) < 0)
        return NULL;
    int seen = seen_before(self, args[0], stamp);
    if (seen < 0)
        return NULL;
    return PyBool_FromLong(seen);
}

static PyObject *streams_last(Streams *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "last(stream, gid) takes 2 arguments");
        return NULL;
    }
    if (check_stream(args[0]) < 0 || check_gid(args[1]) < 0)
        return NULL;
    PyObject *key = PyTuple_Pack(2, args[0], args[1]);
    if (key == NULL)
        return NULL;
    Channel *state = (Channel *)PyDict_GetItemWithError(self->channels, key);
    Py_DECREF(key);
    if (state == NULL) {
        if (PyErr_Occurred())
            return NULL;
        Py_RETURN_NONE;
    }
    return PyLong_FromLongLong(state->last);
}

static PyObject *streams_forget(Streams *self, PyObject *gid) {
    if (check_gid(gid) < 0)
        return NULL;
    if (PyDict_DelItem(self->recent, gid) < 0) {
        if (!PyErr_ExceptionMatches(PyExc_KeyError))
            return NULL;
        PyErr_Clear();
    }
    Py_RETURN_NONE;
}

static PyObject *streams_sizes(Streams *self, PyObject *unused) {
    return Py_BuildValue("(nn)", PyDict_GET_SIZE(self->channels), PyDict_GET_SIZE(self->recent));
}

static PyMethodDef streams_methods[] = {
    {"track", (PyCFunction)(void (*)(void))streams_track, METH_FASTCALL,
     "track(stream, gid, sequence, exact, from_one=False, restarts=False) -> None | "
     "(duplicate, lost, late, jump): judge `sequence` from publisher `gid` on `stream`. `exact`: "
     "the publisher numbers the stream on its own (every step exact); `from_one`: the stream "
     "was started for this reader alone, so a first number past 1 follows that many messages "
     "it missed; `restarts`: a step back is the publisher starting again (a jump), not a late "
     "message. None: in order."},
    {"admit", (PyCFunction)(void (*)(void))streams_admit, METH_FASTCALL,
     "admit(stream, gid, sequence, stamp, exact, from_one, restarts) -> None | (duplicate, "
     "lost, late, jump): seen_before(gid, stamp) (unless stamp is None), then track(...). None: "
     "a new message, in order."},
    {"seen_before", (PyCFunction)(void (*)(void))streams_seen_before, METH_FASTCALL,
     "seen_before(gid, stamp) -> bool: whether a message of `gid` stamped `stamp` arrived "
     "already (among its last 256); otherwise it is remembered."},
    {"last", (PyCFunction)(void (*)(void))streams_last, METH_FASTCALL,
     "last(stream, gid) -> int | None: the last number judged from `gid` on `stream`."},
    {"forget", (PyCFunction)streams_forget, METH_O,
     "forget(gid): drop the stamps remembered of `gid` (its numbers are kept)."},
    {"sizes", (PyCFunction)streams_sizes, METH_NOARGS,
     "sizes() -> (streams tracked, publishers whose stamps are remembered)."},
    {NULL}
};

static PyTypeObject StreamsType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "buffer_pubsub._streams.Streams",
    .tp_basicsize = sizeof(Streams),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Per (stream, publisher) sequence state and per-publisher recent stamps of one "
              "subscription (see the module docstring). Not thread-safe: call under a lock.",
    .tp_new = streams_new,
    .tp_dealloc = (destructor)streams_dealloc,
    .tp_methods = streams_methods,
};

/* ----------------------------------------------------------------------------- module */
static PyObject *configure(PyObject *module, PyObject *args) {
    PyObject *constructor, *error;
    if (!PyArg_ParseTuple(args, "OO", &constructor, &error))
        return NULL;
    if (!PyCallable_Check(constructor)
            || !PyType_Check(error)
            || !PyType_IsSubtype((PyTypeObject *)error, (PyTypeObject *)PyExc_Exception)) {
        PyErr_SetString(PyExc_TypeError,
                        "configure(new_attachment, error_class): a callable and an exception class");
        return NULL;
    }
    Py_XSETREF(new_attachment, Py_NewRef(constructor));
    Py_XSETREF(wire_error, Py_NewRef(error));
    Py_RETURN_NONE;
}

static PyMethodDef module_methods[] = {
    {"configure", configure, METH_VARARGS,
     "configure(new_attachment, error_class): how an attachment is built ((sequence, stamp, "
     "gid) -> Attachment) and the error a malformed one raises (buffer_pubsub.wire does this)."},
    {"parse_attachment", parse_attachment, METH_O,
     "parse_attachment(data) -> Attachment: the 33 bytes rmw_zenoh attaches to a sample (bytes "
     "past them ignored, as rmw_zenoh ignores them)."},
    {"pack_attachment", (PyCFunction)(void (*)(void))pack_attachment, METH_FASTCALL,
     "pack_attachment(sequence, stamp, gid) -> bytes: the 33-byte attachment (int64s, "
     "little-endian; OverflowError past int64, ValueError for a gid not of 16 bytes)."},
    {"split_frame", split_frame, METH_O,
     "split_frame(frame: bytes) -> (Attachment, memoryview): a lane frame's attachment and its "
     "CDR payload (a view of the frame's tail)."},
    {NULL}
};

static struct PyModuleDef streams_module = {
    PyModuleDef_HEAD_INIT, "buffer_pubsub._streams",
    "The per-message checks of an arrival: attachments, sequence numbers, second copies.",
    -1, module_methods,
};

PyMODINIT_FUNC PyInit__streams(void) {
    if (PyType_Ready(&ChannelType) < 0 || PyType_Ready(&RecentType) < 0
            || PyType_Ready(&StreamsType) < 0)
        return NULL;
    PyObject *m = PyModule_Create(&streams_module);
    if (m == NULL)
        return NULL;
    if (PyModule_AddObjectRef(m, "Streams", (PyObject *)&StreamsType) < 0
            || PyModule_AddIntConstant(m, "ATTACHMENT_SIZE", ATTACHMENT_SIZE) < 0
            || PyModule_AddIntConstant(m, "LOST_WINDOW", (long)LOST_WINDOW) < 0
            || PyModule_AddIntConstant(m, "MAX_TRACKED", MAX_TRACKED) < 0
            || PyModule_AddIntConstant(m, "RECENT_STAMPS", RECENT_STAMPS) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
