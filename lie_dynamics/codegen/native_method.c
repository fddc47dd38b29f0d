/* Part of native_call.c (included there, after Bound): a Model method that runs its native
 * kernel straight from C (dispatch.native_first). */
/* ------------------------------------------------------------------ Method: a model's method, native first
 * method(slow, resolve, n_state) is a method descriptor for a Model class. model.NAME(*states)
 * or model.NAME(*states, out=buf) runs the model's Bound kernel straight from C: the kernel
 * is cached in the Method for up to HELD models at a time (for each a weak reference, its
 * `version` then, and the epoch of invalidate()), resolved by resolve(model) -> a Bound, False (no kernel: the
 * slow path, cached) or None (not now: the slow path, not cached). Any other call, a kernel that
 * declines (bad input, non-finite result), or a model without a cached kernel runs
 * slow(model, *args, **kwargs), the Python method, which validates and raises.
 *
 * method(slow, resolve, n_state, 1) is keyed, for methods whose arguments after the per-state
 * arrays choose the kernel (a frame Jacobian's link and frame): model.NAME(*states, *key, **kw)
 * looks the key up in a dict held for the model as above (the key: the arguments after the
 * states, then the keyword names), resolved on a miss by resolve(model, *key, **kw) -> (Bound,
 * tuple of arrays passed after the states), False (the slow path, cached) or None (not cached);
 * a key that cannot be hashed, or resolve raising, runs the slow path. The dict is emptied when
 * it reaches KEYS_MAX keys (many distinct keys: a cache, not a record of every call).
 *
 * method(slow, resolve, n_state, 0, k) with k > 1 is split, for methods that return k (n, n)
 * matrices computed as one kernel output (the derivatives): model.NAME(*states) returns the
 * tuple of views (k n n,) -> k (n, n), or (N, k n n) -> k (N, n, n), n the states' last
 * dimension, as the Python method's reshape and slices give them; it takes no out=. */
static unsigned long epoch = 1;
#define KEYS_MAX 256
#define KEY_ARGS_MAX 8
static PyObject *str_version, *str_out;

/* One model's cached kernel: a weak reference to the model, its `version` then, the kernel (a
 * Bound, or False; keyed: the dict of keys) and the epoch of invalidate() then. */
typedef struct {
    PyObject *model_ref, *version, *kernel;
    unsigned long epoch;
} Held;

/* Models held at once: a process that calls two or three models in turn (a robot and a
 * calibrated copy, a benchmark's peer) resolves each once, not at every switch (~1.5 us). */
#define HELD 4

typedef struct {
    PyObject_HEAD
    vectorcallfunc vectorcall;
    PyObject *slow, *resolve;
    Held held[HELD];
    int next;   /* the entry a new model takes when none is free */
    Py_ssize_t n_state, split;
    int keyed;
} Method;

static PyTypeObject MethodType;

static void held_clear(Held *h)
{
    Py_CLEAR(h->model_ref);
    Py_CLEAR(h->version);
    Py_CLEAR(h->kernel);
}

/* the kernel held for `model` (borrowed), resolved on a miss; NULL: none now (no error set) */
static PyObject *method_kernel(Method *m, PyObject *model)
{
    Held *h = NULL, *free_h = NULL;
    for (int i = 0; i < HELD; ++i) {
        Held *c = &m->held[i];
        PyObject *o = c->model_ref ? PyWeakref_GET_OBJECT(c->model_ref) : NULL;
        if (o == model) {
            h = c;
            break;
        }
        if (!free_h && (!o || o == Py_None))   /* empty, or its model gone */
            free_h = c;
    }
    if (h && h->epoch == epoch) {
        PyObject *v = PyObject_GetAttr(model, str_version);
        if (!v) {
            PyErr_Clear();
            return NULL;
        }
        int same = v == h->version || PyObject_RichCompareBool(v, h->version, Py_EQ) == 1;
        Py_DECREF(v);
        PyErr_Clear();
        if (same)
            return h->kernel;
    }
    if (!h) {
        h = free_h ? free_h : &m->held[m->next];
        if (!free_h)
            m->next = (m->next + 1) % HELD;
    }
    PyObject *k = m->keyed ? PyDict_New() : PyObject_CallOneArg(m->resolve, model);
    /* resolve ran Python: the entries may have changed (another call of this Method); h is
     * still an entry of m, refilled below */
    if (!k) {
        PyErr_Clear();
        return NULL;
    }
    held_clear(h);
    if (k == Py_None) {
        Py_DECREF(k);
        return NULL;
    }
    PyObject *ref = PyWeakref_NewRef(model, NULL), *v = ref ? PyObject_GetAttr(model, str_version) : NULL;
    if (!v) {
        Py_XDECREF(ref);
        Py_DECREF(k);
        PyErr_Clear();
        return NULL;
    }
    for (int i = 0; i < HELD; ++i)   /* one entry per model: another call may have added it meanwhile */
        if (&m->held[i] != h && m->held[i].model_ref && PyWeakref_GET_OBJECT(m->held[i].model_ref) == model)
            held_clear(&m->held[i]);
    h->model_ref = ref;
    h->version = v;
    h->kernel = k;
    h->epoch = epoch;
    return k;
}

/* keyed: the (Bound, extra arrays) of this call's key (args[1 + n_state:], then kwnames) in the dict d,
 * resolved on a miss; a new reference, or NULL (no kernel, no error set) */
static PyObject *method_keyed(Method *m, PyObject *d, PyObject *const *args, Py_ssize_t nargs, PyObject *kwnames)
{
    Py_ssize_t nkw = kwnames ? PyTuple_GET_SIZE(kwnames) : 0, npos = nargs - 1 - m->n_state;
    Py_ssize_t nk = npos + nkw;
    if (nk < 1 || nk > KEY_ARGS_MAX)
        return NULL;
    PyObject *key = PyTuple_New(nk + (nkw > 0));
    if (!key) {
        PyErr_Clear();
        return NULL;
    }
    for (Py_ssize_t i = 0; i < nk; ++i) {
        Py_INCREF(args[1 + m->n_state + i]);
        PyTuple_SET_ITEM(key, i, args[1 + m->n_state + i]);
    }
    if (nkw) {
        Py_INCREF(kwnames);
        PyTuple_SET_ITEM(key, nk, kwnames);
    }
    PyObject *v = PyDict_GetItemWithError(d, key);   /* borrowed */
    if (v) {
        Py_INCREF(v);
    } else if (!PyErr_Occurred()) {
        PyObject *argv[1 + KEY_ARGS_MAX];
        argv[0] = args[0];
        for (Py_ssize_t i = 0; i < nk; ++i)
            argv[1 + i] = args[1 + m->n_state + i];
        v = PyObject_Vectorcall(m->resolve, argv, (size_t)(1 + npos), kwnames);
        if (v == Py_None) {
            Py_CLEAR(v);
        } else if (v) {
            if (PyDict_GET_SIZE(d) >= KEYS_MAX)
                PyDict_Clear(d);
            if (PyDict_SetItem(d, key, v) < 0)
                Py_CLEAR(v);
        }
    }
    Py_DECREF(key);
    PyErr_Clear();   /* an unhashable key, resolve raising: the slow path says what is wrong */
    return v;
}

/* keyed: run the (Bound, extras) v on the states and extras; a new reference: the result, None
 * (declined) or NULL (an error raised) */
static PyObject *method_run_keyed(Method *m, PyObject *v, PyObject *const *states)
{
    if (!PyTuple_Check(v) || PyTuple_GET_SIZE(v) != 2)
        Py_RETURN_NONE;
    PyObject *k = PyTuple_GET_ITEM(v, 0), *extras = PyTuple_GET_ITEM(v, 1);
    if (Py_TYPE(k) != &BoundType || !PyTuple_Check(extras) || m->n_state + PyTuple_GET_SIZE(extras) > MAX_LISTS)
        Py_RETURN_NONE;
    PyObject *argv[MAX_LISTS];
    Py_ssize_t n = 0;
    for (Py_ssize_t i = 0; i < m->n_state; ++i)
        argv[n++] = states[i];
    for (Py_ssize_t i = 0; i < PyTuple_GET_SIZE(extras); ++i)
        argv[n++] = PyTuple_GET_ITEM(extras, i);
    return bound_call(k, argv, (size_t)n, NULL);
}

/* split: the tuple of m->split views of the kernel's result r (stolen), n from the state q; a new
 * reference, or None (a shape that does not split: the slow path) */
static PyObject *method_split(Method *m, PyObject *r, PyObject *q)
{
    if (!PyArray_Check(r) || !PyArray_Check(q)) {
        Py_DECREF(r);
        Py_RETURN_NONE;
    }
    PyArrayObject *a = (PyArrayObject *)r;
    int nd = PyArray_NDIM(a);
    npy_intp n = PyArray_DIM((PyArrayObject *)q, PyArray_NDIM((PyArrayObject *)q) - 1), k = m->split;
    if ((nd != 1 && nd != 2) || PyArray_DIM(a, nd - 1) != k * n * n || !PyArray_IS_C_CONTIGUOUS(a)) {
        Py_DECREF(r);
        Py_RETURN_NONE;
    }
    PyObject *t = PyTuple_New(k);
    npy_intp dims[3], strides[3], row = PyArray_DIM(a, nd - 1) * (npy_intp)sizeof(double);
    int vd = 0;
    if (nd == 2) {
        dims[vd] = PyArray_DIM(a, 0);
        strides[vd++] = row;
    }
    dims[vd] = dims[vd + 1] = n;
    strides[vd] = n * (npy_intp)sizeof(double);
    strides[vd + 1] = sizeof(double);
    vd += 2;
    for (npy_intp i = 0; t && i < k; ++i) {
        PyArray_Descr *d = PyArray_DescrFromType(NPY_DOUBLE);
        PyObject *v = PyArray_NewFromDescr(&PyArray_Type, d, vd, dims, strides,
                                           (char *)PyArray_DATA(a) + i * n * n * (npy_intp)sizeof(double),
                                           NPY_ARRAY_WRITEABLE, NULL);
        if (v) {
            Py_INCREF(r);
            if (PyArray_SetBaseObject((PyArrayObject *)v, r) < 0)
                Py_CLEAR(v);
        }
        if (!v)
            Py_CLEAR(t);
        else
            PyTuple_SET_ITEM(t, i, v);
    }
    Py_DECREF(r);
    return t;
}

static PyObject *method_call(PyObject *self, PyObject *const *args, size_t nargsf, PyObject *kwnames)
{
    Method *m = (Method *)self;
    Py_ssize_t nargs = PyVectorcall_NARGS(nargsf), nkw = kwnames ? PyTuple_GET_SIZE(kwnames) : 0;
    if (m->keyed) {
        PyObject *d = nargs >= 1 + m->n_state ? method_kernel(m, args[0]) : NULL, *v = NULL;
        if (d && PyDict_Check(d)) {   /* held: hashing the key or resolve may run Python that replaces it */
            Py_INCREF(d);
            v = method_keyed(m, d, args, nargs, kwnames);
            Py_DECREF(d);
        }
        if (v) {   /* v holds the Bound and extras while the kernel runs */
            PyObject *r = method_run_keyed(m, v, args + 1);
            Py_DECREF(v);
            if (r != Py_None)
                return r;
            Py_DECREF(r);
        }
        return PyObject_Vectorcall(m->slow, args, nargsf, kwnames);
    }
    if (nargs == 1 + m->n_state && (nkw == 0 || (nkw == 1 && !m->split &&
                                                 PyUnicode_Compare(PyTuple_GET_ITEM(kwnames, 0), str_out) == 0))) {
        PyObject *k = method_kernel(m, args[0]);
        if (k && Py_TYPE(k) == &BoundType) {
            Py_INCREF(k);   /* the cache may change while the kernel runs (another thread, the GIL released) */
            PyObject *r = bound_call(k, args + 1, (size_t)(m->n_state + nkw), NULL);
            Py_DECREF(k);
            if (r && r != Py_None && m->split)
                r = method_split(m, r, args[1]);
            if (r != Py_None)
                return r;   /* the result, or NULL: an error already raised */
            Py_DECREF(r);
        }
    }
    return PyObject_Vectorcall(m->slow, args, nargsf, kwnames);
}

static PyObject *method_get(PyObject *self, PyObject *obj, PyObject *type)
{
    if (obj == NULL || obj == Py_None) {
        Py_INCREF(self);
        return self;
    }
    return PyMethod_New(self, obj);
}

static int method_traverse(PyObject *self, visitproc visit, void *arg)
{
    Method *m = (Method *)self;
    Py_VISIT(m->slow);
    Py_VISIT(m->resolve);
    for (int i = 0; i < HELD; ++i) {
        Py_VISIT(m->held[i].model_ref);
        Py_VISIT(m->held[i].version);
        Py_VISIT(m->held[i].kernel);
    }
    return 0;
}

static int method_clear(PyObject *self)
{
    Method *m = (Method *)self;
    Py_CLEAR(m->slow);
    Py_CLEAR(m->resolve);
    for (int i = 0; i < HELD; ++i)
        held_clear(&m->held[i]);
    return 0;
}

static void method_dealloc(PyObject *self)
{
    PyObject_GC_UnTrack(self);
    method_clear(self);
    Py_TYPE(self)->tp_free(self);
}

/* __doc__, __name__, __qualname__, __module__, __wrapped__: the Python method's */
static PyObject *method_getattro(PyObject *self, PyObject *name)
{
    PyObject *r = PyObject_GenericGetAttr(self, name);
    if (r || !PyErr_ExceptionMatches(PyExc_AttributeError))
        return r;
    PyErr_Clear();
    if (PyUnicode_CompareWithASCIIString(name, "__wrapped__") == 0) {
        Py_INCREF(((Method *)self)->slow);
        return ((Method *)self)->slow;
    }
    return PyObject_GetAttr(((Method *)self)->slow, name);
}

static PyObject *method_doc(PyObject *self, void *closure)
{
    return PyObject_GetAttrString(((Method *)self)->slow, "__doc__");
}

static PyGetSetDef method_getset[] = {
    {"__doc__", method_doc, NULL, NULL, NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

static PyTypeObject MethodType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "lie_dynamics_native.Method",
    .tp_basicsize = sizeof(Method),
    .tp_dealloc = method_dealloc,
    .tp_vectorcall_offset = offsetof(Method, vectorcall),
    .tp_call = PyVectorcall_Call,
    .tp_descr_get = method_get,
    .tp_getattro = method_getattro,
    .tp_getset = method_getset,
    .tp_traverse = method_traverse,
    .tp_clear = method_clear,
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_VECTORCALL | Py_TPFLAGS_METHOD_DESCRIPTOR | Py_TPFLAGS_HAVE_GC,
};

/* method(slow, resolve, n_state[, keyed[, split]]) */
static PyObject *method_new(PyObject *mod, PyObject *args)
{
    PyObject *slow, *resolve;
    Py_ssize_t n_state, split = 0;
    int keyed = 0;
    if (!PyArg_ParseTuple(args, "OOn|pn", &slow, &resolve, &n_state, &keyed, &split))
        return NULL;
    if (n_state < 1 || n_state > MAX_LISTS) {
        PyErr_SetString(PyExc_ValueError, "method: n_state from 1 to 16");
        return NULL;
    }
    if (split < 0 || split == 1 || split > 16 || (split && keyed)) {
        PyErr_SetString(PyExc_ValueError, "method: split 0 or 2 to 16, not keyed");
        return NULL;
    }
    Method *m = PyObject_GC_New(Method, &MethodType);
    if (!m)
        return NULL;
    m->vectorcall = method_call;
    Py_INCREF(slow);
    Py_INCREF(resolve);
    m->slow = slow;
    m->resolve = resolve;
    memset(m->held, 0, sizeof(m->held));
    m->next = 0;
    m->n_state = n_state;
    m->split = split;
    m->keyed = keyed;
    PyObject_GC_Track((PyObject *)m);
    return (PyObject *)m;
}

/* invalidate(): every Method resolves its kernel again (cache.clear, forget, use_native) */
static PyObject *invalidate(PyObject *mod, PyObject *unused)
{
    ++epoch;
    Py_RETURN_NONE;
}
