/* Part of native_call.c (included there, after Method): the dynamics node's fused command path
 * (lie_dynamics/ros/core/fused.py builds it; the rules it follows are the Python path's).
 *
 * command_path(spec) returns a Command for one layout of joint_states, one model version, one
 * desired state and one set of settings; calling it with a serialized joint_states (bytes) does
 * in one call what the node's Python path does for the common case: the decoder's fast-path test
 * (cdr.JointStateDecoder: the same length, encapsulation, bytes from the frame_id to the position
 * count, velocity and effort counts), the positions mapped (messages.JointStateReader: the
 * columns, the range check that also fails NaN, the locked joints in range and unchanged), the law
 * (laws.py: gravity by the model's native kernel, feedforward as its precomputed model term plus
 * the feedback, computed torque by the native inverse dynamics; the operations in numpy's order,
 * -ffp-contract=off: the same bits), the clamp (laws.clamp: within +-bound as computed, else a
 * finite limit exceeded clipped to it, as np.clip) and the command's and ~/commanded_efforts'
 * bytes (cdr.Writer's constant parts joined with the stamp and the clamped efforts). It returns
 * (stamp ns, q, tau as the law computed it, command bytes, joint-state bytes or None, clamped:
 * bool), or None whenever anything differs from that case (a NaN, or an unlimited joint's
 * infinite torque): the caller's Python path then decides, counts and logs as without it; a
 * clamped command is counted and logged by the caller (Compensator.on_fast_command, through
 * laws.clamp itself). It never raises about its input, and runs with the GIL held (one state). */
enum { LAW_GRAVITY = 0, LAW_FEEDFORWARD = 1, LAW_COMPUTED_TORQUE = 2 };

typedef struct {
    PyObject_HEAD
    vectorcallfunc vectorcall;
    Py_ssize_t length, key_end, v_at, e_at, pos_at, vel_at, n_msg, n, n_lock;
    uint32_t v_count, e_count;
    char head[4];
    int law, need_v;
    double locked;                 /* locked joints' bound; NaN: finite is enough */
    const char *key;               /* bytes 12 .. key_end of the layout */
    const npy_intp *cols, *lock_cols;
    const double *lower, *upper, *last_locked, *bound, *limit, *base, *q_d, *qd_d, *qdd_d, *kp, *kd;
    const double *viscous, *coulomb;   /* friction at the measured velocity (gravity, computed torque) */
    double eps;
    PyUFuncGenericFunction tanh_loop;  /* numpy's own float64 tanh loop: np.tanh's bits */
    void *tanh_data;
    PyObject *method, *model;      /* the model's native-first Method (gravity or inverse dynamics) */
    const char *cmd_parts[3], *js_parts[5];
    Py_ssize_t cmd_len[3], js_len[5];
    int js;                        /* ~/commanded_efforts written too */
    PyObject *keep, *desired_keep;
} Command;

static PyTypeObject CommandType;

static inline double f8_at(const char *p)
{
    double v;
    memcpy(&v, p, 8);
    return v;
}

static inline uint32_t u32_at(const char *p)
{
    uint32_t v;
    memcpy(&v, p, 4);
    return v;
}

/* base + Kp (q_d - q) + Kd (qd_d - qd) of joint i, the terms present, in laws.py's order (both laws') */
static double with_feedback(const Command *c, Py_ssize_t i, const double *q, const double *qd, double base)
{
    if (!c->kp && !c->kd)
        return base;
    double fb = 0.0;
    if (c->kp)
        fb = c->kp[i] * (c->q_d[i] - q[i]);
    if (c->kd) {
        double d = c->kd[i] * (c->qd_d[i] - qd[i]);
        fb = c->kp ? fb + d : d;
    }
    return base + fb;
}

/* the model's native kernel for this Method (its cache rule), run on one state; 0: declined */
static int run_method(Command *c, const double *const *in, double *res)
{
    PyObject *k = method_kernel((Method *)c->method, c->model);
    if (!k || Py_TYPE(k) != &BoundType)
        return 0;
    Bound *b = (Bound *)k;
    if (b->n_res != c->n)
        return 0;
    for (int i = 0; i < b->n_in; ++i)
        if (b->width[i] != c->n)
            return 0;
    double stack[512], *out = b->n_out > 512 ? (double *)PyMem_RawMalloc(sizeof(double) * b->n_out) : stack;
    if (!out)
        return 0;
    b->fn(in, b->par, out);
    int ok = accept(b, out);
    if (ok)
        memcpy(res, out, sizeof(double) * c->n);
    if (out != stack)
        PyMem_RawFree(out);
    return ok;
}

/* the parts joined, the efforts (and the stamp) in their places */
static PyObject *join(const char *const *parts, const Py_ssize_t *len, int n_parts, int tau_part, int stamp_part,
                      const double *tau, Py_ssize_t n, const char *stamp)
{
    Py_ssize_t size = 0;
    for (int i = 0; i < n_parts; ++i)
        size += i == tau_part ? 8 * n : i == stamp_part ? 8 : len[i];
    PyObject *r = PyBytes_FromStringAndSize(NULL, size);
    if (!r)
        return NULL;
    char *p = PyBytes_AS_STRING(r);
    for (int i = 0; i < n_parts; ++i) {
        if (i == tau_part) {
            memcpy(p, tau, 8 * n);
            p += 8 * n;
        } else if (i == stamp_part) {
            memcpy(p, stamp, 8);
            p += 8;
        } else {
            memcpy(p, parts[i], len[i]);
            p += len[i];
        }
    }
    return r;
}

static PyObject *command_call(PyObject *self, PyObject *const *args, size_t nargsf, PyObject *kwnames)
{
    Command *c = (Command *)self;
    if (kwnames || PyVectorcall_NARGS(nargsf) != 1 || !PyBytes_CheckExact(args[0]))
        Py_RETURN_NONE;
    const char *buf = PyBytes_AS_STRING(args[0]);
    /* the decoder's fast-path test: the layout of the last message read */
    if (PyBytes_GET_SIZE(args[0]) != c->length || memcmp(buf, c->head, 4) != 0 ||
        memcmp(buf + 12, c->key, c->key_end - 12) != 0 || u32_at(buf + c->v_at) != c->v_count ||
        u32_at(buf + c->e_at) != c->e_count)
        Py_RETURN_NONE;
    Py_ssize_t n = c->n;
    double stack[4 * 64], *q = stack, *qd, *tmp, *tau;
    if (n > 64 && !(q = (double *)PyMem_RawMalloc(sizeof(double) * 4 * n)))
        return PyErr_NoMemory();
    qd = q + n;
    tmp = qd + n;
    tau = tmp + n;
    PyObject *res = NULL;
    int ok = 1;
    const char *pos = buf + c->pos_at;
    for (Py_ssize_t i = 0; i < n && ok; ++i) {   /* messages.JointStateReader.positions */
        double v = q[i] = f8_at(pos + 8 * c->cols[i]);
        ok = c->lower ? (v >= c->lower[i] && v <= c->upper[i]) : (v - v == 0.0);
    }
    for (Py_ssize_t i = 0; i < c->n_lock && ok; ++i) {   /* in range and as last fed to the model */
        double v = f8_at(pos + 8 * c->lock_cols[i]);
        ok = (c->locked == c->locked ? fabs(v) <= c->locked : v - v == 0.0) && v == c->last_locked[i];
    }
    if (ok && c->need_v) {   /* every used velocity present and finite (JointStateReader.velocity) */
        const char *vel = buf + c->vel_at;
        for (Py_ssize_t i = 0; i < n && ok; ++i) {
            double v = qd[i] = f8_at(vel + 8 * c->cols[i]);
            ok = v - v == 0.0;
        }
    }
    if (!ok)
        goto done;
    switch (c->law) {   /* laws.py, operation for operation */
    case LAW_GRAVITY: {
        const double *in[1] = {q};
        ok = run_method(c, in, tau);
        break;
    }
    case LAW_FEEDFORWARD:   /* base = ID(desired) + f(qd_d); + Kp (q_d - q) + Kd (qd_d - qd) */
        for (Py_ssize_t i = 0; i < n; ++i)
            tau[i] = with_feedback(c, i, q, qd, c->base[i]);
        break;
    case LAW_COMPUTED_TORQUE: {   /* ID(q, qd, qdd_d + Kp e + Kd de) */
        for (Py_ssize_t i = 0; i < n; ++i)
            tmp[i] = with_feedback(c, i, q, qd, c->qdd_d[i]);
        const double *in[3] = {q, qd, tmp};
        ok = run_method(c, in, tau);
        break;
    }
    default:
        ok = 0;
    }
    if (ok && (c->viscous || c->coulomb)) {   /* laws.add_friction: tau + (b v + fc tanh(v / eps)) */
        if (c->coulomb) {
            for (Py_ssize_t i = 0; i < n; ++i)
                tmp[i] = qd[i] / c->eps;
            char *targs[2] = {(char *)tmp, (char *)tmp};
            npy_intp tdims[1] = {n}, tsteps[2] = {8, 8};
            c->tanh_loop(targs, tdims, tsteps, c->tanh_data);
        }
        for (Py_ssize_t i = 0; i < n; ++i) {
            double f = 0.0;
            if (c->viscous)
                f = c->viscous[i] * qd[i];
            if (c->coulomb) {
                double cc = c->coulomb[i] * tmp[i];
                f = c->viscous ? f + cc : cc;
            }
            tau[i] = tau[i] + f;
        }
    }
    /* laws.clamp into tmp (free by now): within the bound as computed; a finite limit exceeded
     * (an infinite torque too) clipped to +-limit; a NaN, or an unlimited joint's infinite
     * torque, declined (the Python path refuses it) */
    int clamped = 0;
    for (Py_ssize_t i = 0; i < n && ok; ++i) {
        double t = tau[i], lim = c->limit[i];
        if (fabs(t) <= c->bound[i]) {
            tmp[i] = t;
        } else if (fabs(t) > lim && lim == c->bound[i]) {   /* lim finite (bound = min(lim, DBL_MAX)) */
            tmp[i] = t > 0 ? lim : -lim;
            clamped = 1;
        } else {
            ok = 0;
        }
    }
    if (!ok)
        goto done;
    int32_t sec;
    uint32_t nsec;
    memcpy(&sec, buf + 4, 4);
    memcpy(&nsec, buf + 8, 4);
    int64_t ns = (int64_t)sec * 1000000000 + nsec;
    int64_t s2 = ns >= 0 ? ns / 1000000000 : -((-ns + 999999999) / 1000000000);   /* cdr.stamp_parts: floor */
    if (s2 > INT32_MAX || s2 < INT32_MIN)
        goto done;   /* the Python path says why */
    char stamp[8];
    int32_t s32 = (int32_t)s2;
    uint32_t n32 = (uint32_t)(ns - s2 * 1000000000);
    memcpy(stamp, &s32, 4);
    memcpy(stamp + 4, &n32, 4);
    npy_intp dims[1] = {n};
    PyObject *qa = PyArray_SimpleNew(1, dims, NPY_DOUBLE), *ta = PyArray_SimpleNew(1, dims, NPY_DOUBLE);
    PyObject *cmd = qa && ta ? join(c->cmd_parts, c->cmd_len, 3, 1, -1, tmp, n, NULL) : NULL;
    PyObject *js = cmd && c->js ? join(c->js_parts, c->js_len, 5, 3, 1, tmp, n, stamp) : NULL;
    PyObject *st = cmd && (js || !c->js) ? PyLong_FromLongLong(ns) : NULL;
    if (st) {
        memcpy(PyArray_DATA((PyArrayObject *)qa), q, sizeof(double) * n);
        memcpy(PyArray_DATA((PyArrayObject *)ta), tau, sizeof(double) * n);
        if (!js) {
            Py_INCREF(Py_None);
            js = Py_None;
        }
        res = PyTuple_Pack(6, st, qa, ta, cmd, js, clamped ? Py_True : Py_False);
    }
    Py_XDECREF(qa);
    Py_XDECREF(ta);
    Py_XDECREF(cmd);
    Py_XDECREF(js);
    Py_XDECREF(st);
    if (q != stack)
        PyMem_RawFree(q);
    return res;
done:
    if (q != stack)
        PyMem_RawFree(q);
    Py_RETURN_NONE;
}

static void command_dealloc(PyObject *self)
{
    Command *c = (Command *)self;
    Py_XDECREF(c->method);
    Py_XDECREF(c->model);
    Py_XDECREF(c->keep);
    Py_XDECREF(c->desired_keep);
    Py_TYPE(self)->tp_free(self);
}

/* a float64 vector of n values (or None where allowed: *out NULL) */
static int vector_arg(PyObject *o, Py_ssize_t n, int none_ok, const double **out);

/* desired(base, q_d, qd_d, qdd_d): a new desired state (feedforward: its model term `base` too),
 * without making the Command again (a desired state may come at every state) */
static PyObject *command_desired(PyObject *self, PyObject *args)
{
    Command *c = (Command *)self;
    PyObject *base, *q_d, *qd_d, *qdd_d;
    if (!PyArg_ParseTuple(args, "OOOO", &base, &q_d, &qd_d, &qdd_d))
        return NULL;
    const double *b, *p, *v, *a;
    if (c->law == LAW_GRAVITY || !vector_arg(base, c->n, c->law != LAW_FEEDFORWARD, &b) ||
        !vector_arg(q_d, c->n, 0, &p) || !vector_arg(qd_d, c->n, 0, &v) || !vector_arg(qdd_d, c->n, 0, &a)) {
        PyErr_SetString(PyExc_ValueError, "desired: not the fused command's desired state");
        return NULL;
    }
    PyObject *keep = PyTuple_Pack(4, base, q_d, qd_d, qdd_d);
    if (!keep)
        return NULL;
    c->base = b;
    c->q_d = p;
    c->qd_d = v;
    c->qdd_d = a;
    Py_XSETREF(c->desired_keep, keep);
    Py_RETURN_NONE;
}

static PyMethodDef command_methods[] = {
    {"desired", command_desired, METH_VARARGS, "A new desired state: desired(base, q_d, qd_d, qdd_d)."},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject CommandType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "lie_dynamics_native.Command",
    .tp_basicsize = sizeof(Command),
    .tp_dealloc = command_dealloc,
    .tp_vectorcall_offset = offsetof(Command, vectorcall),
    .tp_call = PyVectorcall_Call,
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_VECTORCALL,
    .tp_methods = command_methods,
    .tp_doc = "The node's fused command path: call(joint_states bytes) -> (stamp, q, tau, command, "
              "joint state, clamped) or None (fused.py)",
};

/* a float64 vector of n values (or None where allowed: *out NULL) */
static int vector_arg(PyObject *o, Py_ssize_t n, int none_ok, const double **out)
{
    if (o == Py_None && none_ok) {
        *out = NULL;
        return 1;
    }
    if (!plain(o, 1, 1) || PyArray_DIM((PyArrayObject *)o, 0) != n)
        return 0;
    *out = (const double *)PyArray_DATA((PyArrayObject *)o);
    return 1;
}

static int index_arg(PyObject *o, Py_ssize_t n, Py_ssize_t limit, const npy_intp **out)
{
    if (!PyArray_Check(o))
        return 0;
    PyArrayObject *a = (PyArrayObject *)o;
    if (PyArray_TYPE(a) != NPY_INTP || PyArray_NDIM(a) != 1 || PyArray_DIM(a, 0) != n || !PyArray_IS_C_CONTIGUOUS(a) ||
        !PyArray_ISALIGNED(a))
        return 0;
    const npy_intp *v = (const npy_intp *)PyArray_DATA(a);
    for (Py_ssize_t i = 0; i < n; ++i)
        if (v[i] < 0 || v[i] >= limit)
            return 0;
    *out = v;
    return 1;
}

static int parts_arg(PyObject *t, int count, const char **parts, Py_ssize_t *len)
{
    if (!PyTuple_Check(t) || PyTuple_GET_SIZE(t) != count)
        return 0;
    for (int i = 0; i < count; ++i) {
        PyObject *p = PyTuple_GET_ITEM(t, i);
        if (!PyBytes_Check(p))
            return 0;
        parts[i] = PyBytes_AS_STRING(p);
        len[i] = PyBytes_GET_SIZE(p);
    }
    return 1;
}

/* command_path(length, head, key, v_at, v_count, e_at, e_count, pos_at, vel_at, n_msg, cols, lower, upper,
 *              lock_cols, last_locked, locked, law, need_v, method, model, base, q_d, qd_d, qdd_d, kp, kd,
 *              bound, limit, cmd_parts, js_parts, keep, viscous, coulomb, eps, np.tanh, its float64 loop's
 *              index):
 * every offset absolute in the message; fused.py */
static PyObject *command_path(PyObject *mod, PyObject *args)
{
    PyObject *viscous, *coulomb, *tanh_ufunc;
    Py_ssize_t tanh_index;
    Py_ssize_t length, v_at, e_at, pos_at, vel_at, n_msg;
    unsigned int v_count, e_count;
    const char *head, *key;
    Py_ssize_t head_len, key_len;
    PyObject *cols, *lower, *upper, *lock_cols, *last_locked, *method, *model, *base, *q_d, *qd_d, *qdd_d, *kp, *kd;
    PyObject *bound, *limit, *cmd_parts, *js_parts, *keep;
    double locked, c_eps;
    int law, need_v;
    if (!PyArg_ParseTuple(args, "ny#y#nInInnnOOOOOdiiOOOOOOOOOOOOOOOdOn", &length, &head, &head_len, &key, &key_len, &v_at,
                          &v_count, &e_at, &e_count, &pos_at, &vel_at, &n_msg, &cols, &lower, &upper, &lock_cols,
                          &last_locked, &locked, &law, &need_v, &method, &model, &base, &q_d, &qd_d, &qdd_d, &kp, &kd,
                          &bound, &limit, &cmd_parts, &js_parts, &keep, &viscous, &coulomb, &c_eps,
                          &tanh_ufunc, &tanh_index))
        return NULL;
    Command *c = PyObject_New(Command, &CommandType);
    if (!c)
        return NULL;
    c->vectorcall = command_call;
    c->method = c->model = c->keep = c->desired_keep = NULL;
    c->length = length;
    c->key_end = 12 + key_len;
    c->v_at = v_at;
    c->e_at = e_at;
    c->pos_at = pos_at;
    c->vel_at = vel_at;
    c->n_msg = n_msg;
    c->v_count = v_count;
    c->e_count = e_count;
    c->key = key;
    c->locked = locked;
    c->law = law;
    c->need_v = need_v;
    Py_ssize_t n = PyArray_Check(cols) ? PyArray_SIZE((PyArrayObject *)cols) : -1;
    c->n = n;
    c->n_lock = PyArray_Check(lock_cols) ? PyArray_SIZE((PyArrayObject *)lock_cols) : -1;
    int ok = head_len == 4 && n > 0 && c->n_lock >= 0 && law >= 0 && law <= 2 && c->key_end <= length &&
             v_at + 4 <= length && e_at + 4 <= length && pos_at + 8 * n_msg <= length &&
             (!need_v || (v_count == n_msg && vel_at + 8 * n_msg <= length)) &&
             index_arg(cols, n, n_msg, &c->cols) && index_arg(lock_cols, c->n_lock, n_msg, &c->lock_cols) &&
             vector_arg(lower, n, 1, &c->lower) && vector_arg(upper, n, c->lower == NULL, &c->upper) &&
             (c->lower == NULL) == (c->upper == NULL) &&
             vector_arg(last_locked, c->n_lock, c->n_lock == 0, &c->last_locked) &&
             vector_arg(bound, n, 0, &c->bound) && vector_arg(limit, n, 0, &c->limit) && vector_arg(base, n, law != LAW_FEEDFORWARD, &c->base) &&
             vector_arg(q_d, n, law == LAW_GRAVITY, &c->q_d) && vector_arg(qd_d, n, law == LAW_GRAVITY, &c->qd_d) &&
             vector_arg(qdd_d, n, law == LAW_GRAVITY, &c->qdd_d) && vector_arg(kp, n, 1, &c->kp) &&
             vector_arg(kd, n, 1, &c->kd) && (!c->kd || need_v) &&
             (law == LAW_FEEDFORWARD || Py_TYPE(method) == &MethodType) &&
             parts_arg(cmd_parts, 3, c->cmd_parts, c->cmd_len);
    ok = ok && vector_arg(viscous, n, 1, &c->viscous) && vector_arg(coulomb, n, 1, &c->coulomb) &&
         (!(c->viscous || c->coulomb) || (need_v && law != LAW_FEEDFORWARD));
    c->eps = c_eps;
    c->tanh_loop = NULL;
    if (ok && c->coulomb) {   /* np.tanh's loop for float64 -> float64 */
        PyUFuncObject *u = (PyUFuncObject *)tanh_ufunc;
        ok = PyObject_TypeCheck(tanh_ufunc, &PyUFunc_Type) && u->nin == 1 && u->nout == 1 && tanh_index >= 0 &&
             tanh_index < u->ntypes && u->types[2 * tanh_index] == NPY_DOUBLE &&
             u->types[2 * tanh_index + 1] == NPY_DOUBLE && u->functions[tanh_index] != NULL;
        if (ok) {
            c->tanh_loop = u->functions[tanh_index];
            c->tanh_data = u->data ? u->data[tanh_index] : NULL;
        }
    }
    c->js = js_parts != Py_None;
    if (ok && c->js)
        ok = parts_arg(js_parts, 5, c->js_parts, c->js_len);
    if (!ok) {
        Py_DECREF(c);
        PyErr_SetString(PyExc_ValueError, "command_path: an argument is not of the fused command's form");
        return NULL;
    }
    memcpy(c->head, head, 4);
    Py_INCREF(method);
    Py_INCREF(model);
    Py_INCREF(keep);
    c->method = method;
    c->model = model;
    c->keep = keep;   /* every array and bytes object the pointers above point into */
    return (PyObject *)c;
}
