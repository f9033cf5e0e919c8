/* buffer_pubsub._loans: a loan's per-message work in C (the rules are buffer_pubsub.loan's
 * module docstring; that module keeps the pools, their keys and the factory calls).
 *
 * - Slot: one pooled message. reusable() gives its buffer fields fresh Buffers (the ones the last
 *   loan handed out become their holders' tokens, watched through weak references) and answers
 *   whether nobody can read the storage: no token alive, and every impl's reclaim() re-armed it.
 * - reuse(slots): the first slot not on loan that is reusable, marked loaned and moved last (the
 *   least recently loaned is probed first), or None.
 * - Loan: the `with publisher.loan(factory) as msg:` context manager.
 *
 * The pool's lock and the GIL serialize calls on one pool's slots. A loan of a reused slot runs
 * one Python frame here (the pool's take), besides the factory's reloan and the publish.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <structmember.h>

static PyObject *buffer_type;  /* rosidl_buffer.Buffer */
static PyObject *loan_error;   /* buffer_pubsub.errors.LoanError */
static PyObject *str_get_impl, *str_impl, *str_reclaim, *str_take, *str_in_blocks;

static int configured(void) {
    if (buffer_type == NULL || loan_error == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "buffer_pubsub._loans is not configured");
        return 0;
    }
    return 1;
}

/* ----------------------------------------------------------------------------- Slot */
typedef struct {
    PyObject_HEAD
    PyObject *msg;
    PyObject *places;  /* tuple of (owner message, field name) */
    PyObject *impls;   /* tuple: the storage of each place, kept */
    PyObject *placed;  /* list: a weak reference to the Buffer this slot put at each place */
    PyObject *handed;  /* list: weak references to Buffers earlier loans handed out (tokens) */
    char loaned;
} Slot;

static PyTypeObject SlotType;

static int slot_init(Slot *self, PyObject *args, PyObject *kwargs) {
    static char *names[] = {"msg", "places", NULL};
    PyObject *msg, *given;
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "OO!:_Slot", names, &msg, &PyList_Type,
                                     &given))
        return -1;
    if (!configured())
        return -1;
    /* A tuple of our own: the caller's list may change, and user code runs in our loops. */
    PyObject *places = PyList_AsTuple(given);
    if (places == NULL)
        return -1;
    Py_ssize_t n = PyTuple_GET_SIZE(places);
    PyObject *impls = PyTuple_New(n), *placed = PyList_New(n), *handed = PyList_New(0);
    if (impls == NULL || placed == NULL || handed == NULL)
        goto fail;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *place = PyTuple_GET_ITEM(places, i);
        if (!PyTuple_Check(place) || PyTuple_GET_SIZE(place) != 2
                || !PyUnicode_Check(PyTuple_GET_ITEM(place, 1))) {
            PyErr_SetString(PyExc_TypeError, "a place is an (owner, field name) tuple");
            goto fail;
        }
        PyObject *buffer = PyObject_GetAttr(PyTuple_GET_ITEM(place, 0),
                                            PyTuple_GET_ITEM(place, 1));
        if (buffer == NULL)
            goto fail;
        PyObject *impl = PyObject_CallMethodNoArgs(buffer, str_get_impl);
        PyObject *ref = impl ? PyWeakref_NewRef(buffer, NULL) : NULL;
        Py_DECREF(buffer);
        if (ref == NULL) {
            Py_XDECREF(impl);
            goto fail;
        }
        PyTuple_SET_ITEM(impls, i, impl);
        PyList_SET_ITEM(placed, i, ref);
    }
    /* Every field replaced before the old ones go (a finalizer run by a decref may call into
     * this slot): its places, impls and placed always come from one init, of one length. */
    PyObject *old[] = {self->msg, self->places, self->impls, self->placed, self->handed};
    self->msg = Py_NewRef(msg);
    self->places = places;
    self->impls = impls;
    self->placed = placed;
    self->handed = handed;
    self->loaned = 1;
    for (size_t i = 0; i < sizeof old / sizeof old[0]; i++)
        Py_XDECREF(old[i]);
    return 0;
fail:
    Py_DECREF(places);
    Py_XDECREF(impls);
    Py_XDECREF(placed);
    Py_XDECREF(handed);
    return -1;
}

static int slot_traverse(Slot *self, visitproc visit, void *arg) {
    Py_VISIT(self->msg);
    Py_VISIT(self->places);
    Py_VISIT(self->impls);
    Py_VISIT(self->placed);
    Py_VISIT(self->handed);
    return 0;
}

static int slot_clear(Slot *self) {
    Py_CLEAR(self->msg);
    Py_CLEAR(self->places);
    Py_CLEAR(self->impls);
    Py_CLEAR(self->placed);
    Py_CLEAR(self->handed);
    return 0;
}

static void slot_dealloc(Slot *self) {
    PyObject_GC_UnTrack(self);
    slot_clear(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* What weak reference `ref` points to now: a new reference, Py_None when it is dead. */
static PyObject *referent(PyObject *ref) {
#if PY_VERSION_HEX >= 0x030D0000
    PyObject *target;
    if (PyWeakref_GetRef(ref, &target) < 0)
        return NULL;
    return target != NULL ? target : Py_NewRef(Py_None);
#else
    return Py_NewRef(PyWeakref_GET_OBJECT(ref));
#endif
}

/* Another Buffer over `current`'s impl (Buffer.share without its frame). */
static PyObject *share(PyObject *current) {
    PyObject *impl = PyObject_GetAttr(current, str_impl);
    if (impl == NULL)
        return NULL;
    PyTypeObject *type = (PyTypeObject *)buffer_type;
    PyObject *fresh = type->tp_alloc(type, 0);
    if (fresh != NULL && PyObject_GenericSetAttr(fresh, str_impl, impl) < 0)
        Py_CLEAR(fresh);
    Py_DECREF(impl);
    return fresh;
}

/* Fresh Buffers in every place (the last loan's become tokens). 0, or -1 on error. The
 * containers are the caller's strong references, from one init (places, impls and placed of
 * one length; placed is never resized): getattr and setattr on the messages run user code,
 * which may even re-initialize the slot. */
static int slot_refresh(PyObject *places, PyObject *impls, PyObject *placed, PyObject *handed) {
    for (Py_ssize_t i = 0; i < PyTuple_GET_SIZE(places); i++) {
        PyObject *place = PyTuple_GET_ITEM(places, i);
        PyObject *owner = PyTuple_GET_ITEM(place, 0), *name = PyTuple_GET_ITEM(place, 1);
        PyObject *mine = Py_NewRef(PyList_GET_ITEM(placed, i));
        PyObject *current = PyObject_GetAttr(owner, name);
        PyObject *last = current ? referent(mine) : NULL;
        PyObject *fresh = NULL;
        if (last != NULL) {
            if (current == last) {  /* handed out with the last loan: now its holders' token */
                if (PyList_Append(handed, mine) == 0)
                    fresh = share(current);
            } else {  /* a Buffer the user put there: not ours, not a token */
                fresh = PyObject_CallOneArg(buffer_type, PyTuple_GET_ITEM(impls, i));
            }
        }
        /* none of our references may stay while the tokens are checked */
        Py_XDECREF(last);
        Py_XDECREF(current);
        Py_DECREF(mine);
        if (fresh == NULL)
            return -1;
        PyObject *ref = PyObject_GenericSetAttr(owner, name, fresh) < 0
                        ? NULL : PyWeakref_NewRef(fresh, NULL);
        Py_DECREF(fresh);
        if (ref == NULL)
            return -1;
        PyList_SetItem(placed, i, ref);  /* steals ref, drops the old one */
    }
    return 0;
}

/* Is any of these weak references alive? 1, 0, or -1 on error. */
static int any_alive(PyObject *refs) {
    for (Py_ssize_t i = 0; i < PyList_GET_SIZE(refs); i++) {
        PyObject *target = referent(PyList_GET_ITEM(refs, i));
        if (target == NULL)
            return -1;
        int alive = target != Py_None;
        Py_DECREF(target);
        if (alive)
            return 1;
    }
    return 0;
}

/* 1: nobody can read the storage, 0: somebody may, -1: error. */
static int slot_reusable_c(Slot *self) {
    PyObject *places = Py_NewRef(self->places), *impls = Py_NewRef(self->impls);
    PyObject *placed = Py_NewRef(self->placed), *handed = Py_NewRef(self->handed);
    int done = slot_refresh(places, impls, placed, handed) < 0 ? -1 : 1;
    if (done > 0 && PyList_GET_SIZE(handed)) {
        int alive = any_alive(handed);
        if (alive != 0)
            done = alive < 0 ? -1 : 0;
        else if (PyList_SetSlice(handed, 0, PyList_GET_SIZE(handed), NULL) < 0)
            done = -1;
    }
    for (Py_ssize_t i = 0; done > 0 && i < PyTuple_GET_SIZE(impls); i++) {
        PyObject *r = PyObject_CallMethodNoArgs(PyTuple_GET_ITEM(impls, i), str_reclaim);
        done = r == NULL ? -1 : PyObject_IsTrue(r);
        Py_XDECREF(r);
    }
    Py_DECREF(places);
    Py_DECREF(impls);
    Py_DECREF(placed);
    Py_DECREF(handed);
    return done;
}

static PyObject *slot_reusable(Slot *self, PyObject *unused) {
    if (self->places == NULL) {
        PyErr_SetString(PyExc_ValueError, "an uninitialized slot");
        return NULL;
    }
    int done = slot_reusable_c(self);
    return done < 0 ? NULL : PyBool_FromLong(done);
}

static PyMethodDef slot_methods[] = {
    {"reusable", (PyCFunction)slot_reusable, METH_NOARGS,
     "Nobody can read the storage: no Buffer an earlier loan handed out is alive, and every "
     "backend re-armed its memory. First the message's buffer fields get fresh Buffers."},
    {NULL}
};

static PyMemberDef slot_members[] = {
    {"msg", T_OBJECT, offsetof(Slot, msg), READONLY, "the pooled message"},
    {"impls", T_OBJECT, offsetof(Slot, impls), READONLY, "the storage of each buffer field"},
    {"loaned", T_BOOL, offsetof(Slot, loaned), 0, "on loan now"},
    {NULL}
};

static PyTypeObject SlotType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "buffer_pubsub.loan._Slot",
    .tp_basicsize = sizeof(Slot),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
    .tp_doc = "_Slot(msg, places): one pooled message, where its buffers sit (a list of (owner, "
              "field name)), the storage they hold (kept), the Buffers it put there (weakly) and "
              "those earlier loans handed out (their holders' tokens).",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)slot_init,
    .tp_traverse = (traverseproc)slot_traverse,
    .tp_clear = (inquiry)slot_clear,
    .tp_dealloc = (destructor)slot_dealloc,
    .tp_methods = slot_methods,
    .tp_members = slot_members,
};

/* reuse(slots): see the module comment (call with the pool's lock held). */
static PyObject *reuse(PyObject *module, PyObject *slots) {
    if (!PyList_Check(slots)) {
        PyErr_Format(PyExc_TypeError, "reuse() takes a list of slots, not %.100s",
                     Py_TYPE(slots)->tp_name);
        return NULL;
    }
    for (Py_ssize_t i = 0; i < PyList_GET_SIZE(slots); i++) {
        PyObject *item = PyList_GET_ITEM(slots, i);
        if (!PyObject_TypeCheck(item, &SlotType)) {
            PyErr_Format(PyExc_TypeError, "reuse() takes slots, not %.100s",
                         Py_TYPE(item)->tp_name);
            return NULL;
        }
        Slot *slot = (Slot *)item;
        if (slot->loaned || slot->places == NULL)
            continue;
        Py_INCREF(slot);  /* the list may change under the calls reusable makes */
        int done = slot_reusable_c(slot);
        if (done != 0) {
            if (done > 0) {
                slot->loaned = 1;
                Py_ssize_t at = PySequence_Index(slots, item);  /* (where it is now) */
                if (at < 0 || PySequence_DelItem(slots, at) < 0
                        || PyList_Append(slots, item) < 0)
                    done = -1;
            }
            if (done < 0) {
                Py_DECREF(slot);
                return NULL;
            }
            return (PyObject *)slot;
        }
        Py_DECREF(slot);
    }
    Py_RETURN_NONE;
}

/* ----------------------------------------------------------------------------- Loan */
typedef struct {
    PyObject_HEAD
    PyObject *pool, *publish, *factory, *max_loans, *msg, *slot;
} Loan;

static int loan_init(Loan *self, PyObject *args, PyObject *kwargs) {
    static char *names[] = {"pool", "publish", "factory", "max_loans", NULL};
    PyObject *pool, *publish, *factory, *max_loans = Py_None;
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "OOO|O:Loan", names, &pool, &publish,
                                     &factory, &max_loans))
        return -1;
    if (!PyCallable_Check(publish) || !PyCallable_Check(factory)) {
        PyErr_SetString(PyExc_TypeError, "Loan(pool, publish, factory): publish and factory "
                                         "are callables");
        return -1;
    }
    Py_XSETREF(self->pool, Py_NewRef(pool));
    Py_XSETREF(self->publish, Py_NewRef(publish));
    Py_XSETREF(self->factory, Py_NewRef(factory));
    Py_XSETREF(self->max_loans, Py_NewRef(max_loans));
    Py_CLEAR(self->msg);
    Py_CLEAR(self->slot);
    return 0;
}

static int loan_traverse(Loan *self, visitproc visit, void *arg) {
    Py_VISIT(self->pool);
    Py_VISIT(self->publish);
    Py_VISIT(self->factory);
    Py_VISIT(self->max_loans);
    Py_VISIT(self->msg);
    Py_VISIT(self->slot);
    return 0;
}

static int loan_clear(Loan *self) {
    Py_CLEAR(self->pool);
    Py_CLEAR(self->publish);
    Py_CLEAR(self->factory);
    Py_CLEAR(self->max_loans);
    Py_CLEAR(self->msg);
    Py_CLEAR(self->slot);
    return 0;
}

static void loan_dealloc(Loan *self) {
    PyObject_GC_UnTrack(self);
    loan_clear(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* The pool's set of the ids of messages inside an open block (a new reference). */
static PyObject *in_blocks(Loan *self) {
    PyObject *found = PyObject_GetAttr(self->pool, str_in_blocks);
    if (found != NULL && !PySet_Check(found)) {
        PyErr_SetString(PyExc_TypeError, "a loan pool's in_blocks is a set");
        Py_CLEAR(found);
    }
    return found;
}

static PyObject *loan_enter(Loan *self, PyObject *unused) {
    if (!configured())
        return NULL;
    if (self->pool == NULL) {
        PyErr_SetString(PyExc_ValueError, "an uninitialized Loan");
        return NULL;
    }
    if (self->msg != NULL) {
        PyErr_SetString(loan_error,
                        "a Loan is entered once; call publisher.loan(...) for the next one");
        return NULL;
    }
    PyObject *taken = PyObject_CallMethodObjArgs(self->pool, str_take, self->factory,
                                                 self->max_loans, NULL);
    if (taken == NULL)
        return NULL;
    if (!PyTuple_Check(taken) || PyTuple_GET_SIZE(taken) != 2) {
        Py_DECREF(taken);
        PyErr_SetString(PyExc_TypeError, "a loan pool's take returns (message, slot)");
        return NULL;
    }
    PyObject *msg = PyTuple_GET_ITEM(taken, 0), *slot = PyTuple_GET_ITEM(taken, 1);
    if (slot != Py_None && !PyObject_TypeCheck(slot, &SlotType)) {
        Py_DECREF(taken);
        PyErr_SetString(PyExc_TypeError, "a loan pool's take returns (message, _Slot or None)");
        return NULL;
    }
    Py_INCREF(msg);  /* ours until returned: the getattr below may run code that ends the loan */
    Py_XSETREF(self->msg, Py_NewRef(msg));
    Py_XSETREF(self->slot, slot == Py_None ? NULL : Py_NewRef(slot));
    Py_DECREF(taken);
    PyObject *blocks = in_blocks(self);
    PyObject *id = blocks ? PyLong_FromVoidPtr(msg) : NULL;
    int added = id ? PySet_Add(blocks, id) : -1;
    Py_XDECREF(id);
    Py_XDECREF(blocks);
    if (added < 0) {  /* no loan then: no __exit__ will come for it */
        Py_CLEAR(self->msg);
        Py_CLEAR(self->slot);
        Py_DECREF(msg);
        return NULL;
    }
    return msg;
}

static PyObject *loan_exit(Loan *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 3) {
        PyErr_Format(PyExc_TypeError, "__exit__ takes 3 arguments, got %zd", nargs);
        return NULL;
    }
    PyObject *msg = self->msg, *slot = self->slot;  /* (ours now: the fields are cleared) */
    self->msg = self->slot = NULL;
    int failed = 0;
    if (msg != NULL && self->pool != NULL) {
        PyObject *blocks = in_blocks(self);
        PyObject *id = blocks ? PyLong_FromVoidPtr(msg) : NULL;
        failed = id == NULL || PySet_Discard(blocks, id) < 0;
        Py_XDECREF(id);
        Py_XDECREF(blocks);
        if (!failed && args[0] == Py_None) {
            PyObject *r = PyObject_CallOneArg(self->publish, msg);
            failed = r == NULL;
            Py_XDECREF(r);
        }
    }
    if (slot != NULL)
        ((Slot *)slot)->loaned = 0;  /* the loan ended (published or abandoned) */
    Py_XDECREF(msg);
    Py_XDECREF(slot);
    if (failed)
        return NULL;
    Py_RETURN_NONE;  /* an exception in the block propagates */
}

static PyMethodDef loan_methods[] = {
    {"__enter__", (PyCFunction)loan_enter, METH_NOARGS, "The loaned message."},
    {"__exit__", (PyCFunction)(void (*)(void))loan_exit, METH_FASTCALL,
     "Publish the message (nothing on an exception), then give the slot back."},
    {NULL}
};

static PyTypeObject LoanType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "buffer_pubsub.loan.Loan",
    .tp_basicsize = sizeof(Loan),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
    .tp_doc = "``with publisher.loan(factory) as msg:`` (see the module buffer_pubsub.loan).\n\n"
              "The message is the publisher's until the block ends: on a normal exit it is "
              "published (the loan ends at publish: buffers are sealed, and a backend may make a "
              "view kept past it unwritable, as warp_buffer does on its cpu device); on an "
              "exception nothing is published and the message goes back to the pool. A loaned "
              "message published intra-process is not reused while any subscriber still holds "
              "it (its snapshot holds the loan's ``Buffer``).\n\n"
              "Loan(pool, publish, factory, max_loans=None) is made by Publisher.loan.",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)loan_init,
    .tp_traverse = (traverseproc)loan_traverse,
    .tp_clear = (inquiry)loan_clear,
    .tp_dealloc = (destructor)loan_dealloc,
    .tp_methods = loan_methods,
};

/* ----------------------------------------------------------------------------- module */
static PyObject *configure(PyObject *module, PyObject *args) {
    PyObject *buffer, *error;
    if (!PyArg_ParseTuple(args, "O!O!", &PyType_Type, &buffer, &PyType_Type, &error))
        return NULL;
    if (!PyType_IsSubtype((PyTypeObject *)error, (PyTypeObject *)PyExc_Exception)) {
        PyErr_SetString(PyExc_TypeError, "configure(Buffer, LoanError): a class and an "
                                         "exception class");
        return NULL;
    }
    Py_XSETREF(buffer_type, Py_NewRef(buffer));
    Py_XSETREF(loan_error, Py_NewRef(error));
    Py_RETURN_NONE;
}

static PyMethodDef module_methods[] = {
    {"configure", configure, METH_VARARGS,
     "configure(Buffer, LoanError): the Buffer class a slot hands out and the error of a Loan "
     "entered twice (buffer_pubsub.loan does this)."},
    {"reuse", reuse, METH_O,
     "reuse(slots) -> the first slot not on loan that is reusable (marked loaned, moved last), "
     "or None."},
    {NULL}
};

static struct PyModuleDef loans_module = {
    PyModuleDef_HEAD_INIT, "buffer_pubsub._loans",
    "A loan's per-message work: pooled slots, their tokens, the Loan context manager.",
    -1, module_methods,
};

PyMODINIT_FUNC PyInit__loans(void) {
    if (PyType_Ready(&SlotType) < 0 || PyType_Ready(&LoanType) < 0)
        return NULL;
    struct { PyObject **slot; const char *text; } strings[] = {
        {&str_get_impl, "get_impl"}, {&str_impl, "_impl"}, {&str_reclaim, "reclaim"},
        {&str_take, "take"}, {&str_in_blocks, "in_blocks"},
    };
    for (size_t i = 0; i < sizeof strings / sizeof strings[0]; i++)
        if (*strings[i].slot == NULL
                && (*strings[i].slot = PyUnicode_InternFromString(strings[i].text)) == NULL)
            return NULL;
    PyObject *m = PyModule_Create(&loans_module);
    if (m == NULL)
        return NULL;
    if (PyModule_AddObjectRef(m, "_Slot", (PyObject *)&SlotType) < 0
            || PyModule_AddObjectRef(m, "Loan", (PyObject *)&LoanType) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
