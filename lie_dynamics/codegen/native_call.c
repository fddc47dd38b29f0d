/* The call path of the native kernels (codegen/native.py): one small CPython extension,
 * compiled once per Python, numpy and compiler, shared by every generated kernel.
 *
 * bind(...) returns a Bound: a kernel's address (a plain C library made by native.py from
 * crender.py's source) with its parameter lists pre-bound. Calling it with the per-state
 * arrays (and optionally `out`) runs the kernel for one state (n,) or a batch (N, n), the
 * batch over rows with the GIL released. It takes only the common case, contiguous float64
 * arrays of the right shapes and a finite (and, for forward dynamics, positive definite)
 * result; otherwise it returns None and the caller's full path validates, names the bad
 * argument or falls back to the reference: the fast path never raises about its inputs.
 *
 * A batch runs in blocks of LANES states through the kernel's form across states (clanes.py)
 * when it has one, the rest state by state; each state's outputs equal the one-state kernel's
 * to the bit. From 2 * thread_rows states it runs on up to n_threads POSIX threads (set_threads;
 * native.set_threads), which take its rows a part at a time (take_parts), each writing its own:
 * the same results.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#define NPY_NO_DEPRECATED_API NPY_1_7_API_VERSION
#include <numpy/arrayobject.h>
#include <numpy/ufuncobject.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>
#include <pthread.h>
#include <time.h>

#define MAX_LISTS 16
#define MAX_SINCOS 64   /* inputs whose sin and cos a form across states takes computed */
#define SC_CHUNK 256    /* states whose sin and cos are computed together */
#define SC_KEYS 48      /* sincos_grouped's groups */

typedef void (*kernel_fn)(const double *const *in, const double *const *par, double *out);
/* the form across states (clanes.py): 1 when every output is finite */
typedef int (*lanes_kernel_fn)(const double *const *in, const double *const *par, double *out);

typedef struct {
    PyObject_HEAD
    vectorcallfunc vectorcall;
    kernel_fn fn;           /* one state */
    lanes_kernel_fn lanes_fn;   /* LANES states at once (clanes.py), or NULL */
    int n_in, n_par, out_nd, check, lanes;
    int n_sc, sc_list[MAX_SINCOS];   /* lanes_fn's in[n_in], in[n_in + 1]: sin and cos of these inputs */
    Py_ssize_t sc_pos[MAX_SINCOS];
    Py_ssize_t width[MAX_LISTS];
    const double *par[MAX_LISTS];
    npy_intp out_dims[2];
    Py_ssize_t n_out, n_res, gil_rows;
    double rtol;
    PyObject *keep;
} Bound;

/* set_threads: batches of at least 2 * thread_rows states are cut among up to n_threads threads */
static int n_threads = 1;
static Py_ssize_t thread_rows = 1024;

/* 1: the n values at v are all finite (their sum is: an inf or a NaN makes it so; values whose
 * sum overflows count as not finite), summed in 8 independent chains held in registers */
static int all_finite(const double *v, Py_ssize_t n)
{
    double p0 = 0.0, p1 = 0.0, p2 = 0.0, p3 = 0.0, p4 = 0.0, p5 = 0.0, p6 = 0.0, p7 = 0.0;
    Py_ssize_t k = 0;
    for (; k + 8 <= n; k += 8) {   /* scalars, not an array: kept in registers */
        p0 += v[k];
        p1 += v[k + 1];
        p2 += v[k + 2];
        p3 += v[k + 3];
        p4 += v[k + 4];
        p5 += v[k + 5];
        p6 += v[k + 6];
        p7 += v[k + 7];
    }
    for (; k < n; ++k)
        p0 += v[k];
    double s = ((p0 + p1) + (p2 + p3)) + ((p4 + p5) + (p6 + p7));
    return s - s == 0.0;
}

/* 1: the result is finite (and, check 1, every pivot out[n_res + i] > rtol * out[n_res + m + i]).
 * Finite: the sum, taken in 8 partial sums (independent additions: a 6 x 200 Jacobian's check
 * took as long as its kernel as one chain of 1,200 dependent additions). */
static int accept(const Bound *b, const double *v)
{
    if (!all_finite(v, b->n_res))
        return 0;
    if (b->check) {
        Py_ssize_t m = (b->n_out - b->n_res) / 2;
        const double *piv = v + b->n_res, *scale = piv + m;
        for (Py_ssize_t i = 0; i < m; ++i)
            if (!(piv[i] > b->rtol * scale[i]))
                return 0;
    }
    return 1;
}

/* rows [r0, r1) state by state; tmp: n_out doubles when n_out > n_res, else NULL */
static int run_rows(const Bound *b, char **data, npy_intp r0, npy_intp r1, double *res, double *tmp)
{
    const double *in[MAX_LISTS];
    for (npy_intp r = r0; r < r1; ++r) {
        for (int i = 0; i < b->n_in; ++i)
            in[i] = (const double *)data[i] + r * b->width[i];
        double *row = res + r * b->n_res;
        if (tmp) {
            b->fn(in, b->par, tmp);
            memcpy(row, tmp, sizeof(double) * b->n_res);
            if (!accept(b, tmp))
                return 0;
        } else {
            b->fn(in, b->par, row);
            if (!accept(b, row))
                return 0;
        }
    }
    return 1;
}

/* The AVX2 form across states returns with the upper halves of the vector registers in use (gcc
 * emits no vzeroupper below -O2, and the kernels are built at -O1): SSE code after it, here, in
 * the C library, the interpreter and Pinocchio, then ran slower until something cleared them (an
 * AMD Zen 4, bench.probes.batch_sincos: one-state calls 1.5x, pin.rnea 1.26x). clear_upper()
 * clears them after each call, where the CPU has AVX (vzeroupper keeps the low 128 bits, all that
 * SSE code holds). */
static int has_avx;

static inline void clear_upper(void)
{
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
    if (has_avx)
        __asm__ volatile("vzeroupper" ::: "memory");
#endif
}

/* *s, *c = sin(x), cos(x): glibc's sincos where there is one, else the two calls (the same values) */
static inline void sincos1(double x, double *s, double *c)
{
#ifdef __GLIBC__
    sincos(x, s, c);
#else
    *s = sin(x);
    *c = cos(x);
#endif
}

/* sincos_grouped's group of x: what glibc's sin and cos branch on (the range |x| < 0.855469, <
 * 2.426265 or above, the quadrant, whether x lies within 0.126 of a multiple of pi/2, and on which
 * side), computed without branches */
static inline int sincos_key(double x)
{
    const double toint = 6755399441055744.0;   /* 1.5 * 2^52: t + toint rounds t to an integer */
    double a = fabs(x), t = x * 0.63661977236758134308, v = t + toint, d = t - (v - toint);
    uint64_t bits;
    memcpy(&bits, &v, sizeof bits);
    int range = (a >= 0.855469) + (a >= 2.426265);
    return ((range * 4 + (int)(bits & 3)) * 2 + (fabs(d) < 0.0802)) * 2 + (d < 0.0);
}

/* s[i], c[i] = sin(x[i]), cos(x[i]) for i < n, called in the order of their groups (a counting
 * sort; key, order: n entries of scratch). In a batch the branches of the C library's sin and cos
 * are random and mostly mispredicted: a 7-joint arm's angles took 23 ns a call in their order and
 * 14 ns grouped (bench.probes.batch_sincos). The order changes no value. */
static void sincos_grouped(const double *x, Py_ssize_t n, double *s, double *c, unsigned char *key, int *order)
{
    Py_ssize_t start[SC_KEYS + 1] = {0};
    for (Py_ssize_t i = 0; i < n; ++i) {
        key[i] = (unsigned char)sincos_key(x[i]);
        ++start[key[i] + 1];
    }
    for (int k = 0; k < SC_KEYS; ++k)
        start[k + 1] += start[k];
    for (Py_ssize_t i = 0; i < n; ++i)
        order[start[key[i]]++] = (int)i;
    for (Py_ssize_t j = 0; j < n; ++j) {   /* into locals: faster than through &s[i], &c[i] */
        int i = order[j];
        double si, ci;
        sincos1(x[i], &si, &ci);
        s[i] = si;
        c[i] = ci;
    }
}

/* rows [r0, r1): blocks of `lanes` consecutive states through lanes_fn, which reads their rows and
 * writes theirs (n_out values a state) and answers whether every output is finite; the rest state
 * by state. The sin and cos lanes_fn takes computed come from sincos_grouped, SC_CHUNK states at a
 * time. With more outputs than the result or a pivot test, a block goes through a buffer and
 * accept, state by state. 0: a state failed, -1: no memory. */
static int run(const Bound *b, char **data, npy_intp r0, npy_intp r1, double *res)
{
    Py_ssize_t L = b->lanes;
    npy_intp full = b->lanes_fn && L > 1 ? r0 + (r1 - r0) / L * L : r0;
    int direct = b->n_out == b->n_res && !b->check;
    Py_ssize_t chunk = SC_CHUNK / L * L, n_sc = full > r0 ? chunk * b->n_sc : 0;
    Py_ssize_t total = b->n_out + (full > r0 && !direct ? b->n_out * L : 0) + 3 * n_sc;
    size_t bytes = sizeof(double) * (size_t)total + (sizeof(int) + 1) * (size_t)n_sc;
    double stack[2048], *buf = stack;
    if (bytes > sizeof stack && !(buf = (double *)PyMem_RawMalloc(bytes)))
        return -1;
    double *tmp = b->n_out > b->n_res ? buf : NULL, *blk = buf + b->n_out;
    double *x = blk + (full > r0 && !direct ? b->n_out * L : 0), *sn = x + n_sc, *cs = sn + n_sc;
    int *order = (int *)(cs + n_sc);
    unsigned char *key = (unsigned char *)(order + n_sc);
    const double *in[MAX_LISTS + 2];
    int ok = 1;
    for (npy_intp c0 = r0; c0 < full && ok; c0 += chunk) {
        npy_intp c1 = c0 + chunk < full ? c0 + chunk : full;
        Py_ssize_t m = (c1 - c0) * b->n_sc;
        for (npy_intp r = c0; r < c1; ++r)
            for (int j = 0; j < b->n_sc; ++j)
                x[(r - c0) * b->n_sc + j] =
                    ((const double *)data[b->sc_list[j]])[r * b->width[b->sc_list[j]] + b->sc_pos[j]];
        sincos_grouped(x, m, sn, cs, key, order);
        for (npy_intp r = c0; r < c1 && ok; r += L) {
            for (int i = 0; i < b->n_in; ++i)
                in[i] = (const double *)data[i] + r * b->width[i];
            in[b->n_in] = sn + (r - c0) * b->n_sc;
            in[b->n_in + 1] = cs + (r - c0) * b->n_sc;
            if (direct) {
                ok = b->lanes_fn(in, b->par, res + r * b->n_res);
                clear_upper();
                continue;
            }
            b->lanes_fn(in, b->par, blk);
            clear_upper();
            for (Py_ssize_t l = 0; l < L && ok; ++l) {
                memcpy(res + (r + l) * b->n_res, blk + l * b->n_out, sizeof(double) * b->n_res);
                ok = accept(b, blk + l * b->n_out);
            }
        }
    }
    if (ok)
        ok = run_rows(b, data, full, r1, res, tmp);
    if (buf != stack)
        PyMem_RawFree(buf);
    return ok;
}

/* A threaded batch's rows, handed out a part at a time to whichever thread asks next: a thread
 * that starts late (a core woken from idle, a machine shared with other jobs) takes fewer parts,
 * instead of the others waiting for its equal share at the end (bench.calls: 2 threads read
 * 1.0-1.5x one thread with equal halves on an otherwise quiet machine). A part is the rows left
 * over twice the threads (guided scheduling: large parts first, small ones at the end, so the
 * threads finish together), at least MIN_PART, in whole blocks of lanes; run() gives each state
 * the same bits whatever part it falls in. */
#define MIN_PART 64

typedef struct {
    const Bound *b;
    char **data;
    double *res;
    npy_intp N, next;   /* next: the first row not yet taken (atomic) */
    int threads;
    int ok;             /* 1, or the first failing part's run() answer (atomic): the rest stop */
} Parts;

static void take_parts(Parts *s)
{
    for (;;) {
        if (__atomic_load_n(&s->ok, __ATOMIC_RELAXED) != 1)
            return;
        npy_intp r0 = __atomic_load_n(&s->next, __ATOMIC_RELAXED), size;
        do {
            if (r0 >= s->N)
                return;
            size = (s->N - r0) / (2 * s->threads) / 8 * 8;
            if (size < MIN_PART)
                size = MIN_PART;
        } while (!__atomic_compare_exchange_n(&s->next, &r0, r0 + size, 1, __ATOMIC_RELAXED, __ATOMIC_RELAXED));
        int ok = run(s->b, s->data, r0, r0 + size < s->N ? r0 + size : s->N, s->res);
        if (ok != 1) {
            int one = 1;
            __atomic_compare_exchange_n(&s->ok, &one, ok, 0, __ATOMIC_RELAXED, __ATOMIC_RELAXED);
            return;
        }
    }
}

/* The helpers of threaded batches: started by the first one and kept, as an OpenMP runtime keeps
 * its team (pin.rneaInParallel's). Between batches a helper spins for SPIN_NS, so that a batch
 * right after another finds it on its core, then sleeps on a condition variable. Starting a thread
 * for each batch cost tens of us, and its first part waited for a core woken from idle:
 * bench.calls read 2 threads at 1.59-1.77x one thread at N = 10,000 on the quiet machine, against
 * 1.87-1.94x for rneaInParallel. A batch offers its Parts to up to `limit` helpers through `word`:
 * the helpers in it, or WORD_CLOSED once the batch has ended (its Parts live on the caller's
 * stack: a helper joins only by moving word from below limit, so none touches them after). One
 * batch uses the helpers at a time (`busy`); another at the same moment starts its own threads. */
#define SPIN_NS 200000L
#define WORD_CLOSED (-1)

static struct {
    pthread_mutex_t busy, m;   /* busy: a batch holds the helpers; m, cv: sleeping helpers */
    pthread_cond_t cv;
    unsigned gen;              /* bumped to offer a batch (atomic) */
    int word, limit, sleepers; /* atomic */
    Parts *job;
    int started;               /* helpers running */
} pool = {.busy = PTHREAD_MUTEX_INITIALIZER, .m = PTHREAD_MUTEX_INITIALIZER, .cv = PTHREAD_COND_INITIALIZER,
        .word = WORD_CLOSED};

static inline void relax(void)
{
#if defined(__x86_64__) || defined(__i386__)
    __builtin_ia32_pause();
#elif defined(__aarch64__)
    __asm__ volatile("yield");
#endif
}

static long now_ns(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return t.tv_sec * 1000000000L + t.tv_nsec;
}

/* join the batch on offer, if it still takes helpers, and take its parts */
static void join_batch(void)
{
    int w = __atomic_load_n(&pool.word, __ATOMIC_ACQUIRE);
    do {
        if (w == WORD_CLOSED || w >= __atomic_load_n(&pool.limit, __ATOMIC_RELAXED))
            return;
    } while (!__atomic_compare_exchange_n(&pool.word, &w, w + 1, 1, __ATOMIC_ACQUIRE, __ATOMIC_ACQUIRE));
    take_parts(pool.job);
    __atomic_fetch_sub(&pool.word, 1, __ATOMIC_RELEASE);   /* its rows and answer are seen after */
}

static void *helper_main(void *arg)
{
    unsigned seen = (unsigned)(uintptr_t)arg;
    for (;;) {
        unsigned g;
        long t0 = now_ns();
        for (int i = 0; (g = __atomic_load_n(&pool.gen, __ATOMIC_SEQ_CST)) == seen; ++i) {
            if ((i & 255) == 255 && now_ns() - t0 > SPIN_NS)
                break;
            relax();
        }
        if (g == seen) {   /* gen, then sleepers (seq_cst), as run_pooled writes and reads them: no lost wake-up */
            pthread_mutex_lock(&pool.m);
            __atomic_fetch_add(&pool.sleepers, 1, __ATOMIC_SEQ_CST);
            while ((g = __atomic_load_n(&pool.gen, __ATOMIC_SEQ_CST)) == seen)
                pthread_cond_wait(&pool.cv, &pool.m);
            __atomic_fetch_sub(&pool.sleepers, 1, __ATOMIC_SEQ_CST);
            pthread_mutex_unlock(&pool.m);
        }
        seen = g;
        join_batch();
    }
    return NULL;
}

/* a forked child has none of its parent's threads, and their locks may have been held at the fork */
static void pool_after_fork(void)
{
    pthread_mutex_init(&pool.busy, NULL);
    pthread_mutex_init(&pool.m, NULL);
    pthread_cond_init(&pool.cv, NULL);
    pool.word = WORD_CLOSED;
    pool.sleepers = 0;
    pool.started = 0;
}

static void *once_main(void *arg)
{
    take_parts((Parts *)arg);
    return NULL;
}

/* rows [0, N) on T threads, each started for this batch (the helpers are in use, or could not start) */
static int run_started(Parts *s, int T)
{
    pthread_t ids[64];
    int started = 0;
    for (int t = 1; t < T; ++t)   /* a thread that fails to start leaves its parts to the others */
        started += pthread_create(&ids[started], NULL, once_main, s) == 0;
    take_parts(s);
    for (int t = 0; t < started; ++t)
        pthread_join(ids[t], NULL);   /* a barrier: every part's rows and answer are seen here */
    return s->ok;
}

/* rows [0, N) on the kept helpers and this thread; -2 when the helpers are another batch's */
static int run_pooled(Parts *s, int T)
{
    if (pthread_mutex_trylock(&pool.busy) != 0)
        return -2;
    unsigned gen = __atomic_load_n(&pool.gen, __ATOMIC_RELAXED);
    if (pool.started < T - 1) {   /* the first batch with this many threads: start the helpers missing */
        pthread_attr_t attr;
        pthread_attr_init(&attr);
        pthread_attr_setdetachstate(&attr, PTHREAD_CREATE_DETACHED);
        while (pool.started < T - 1) {
            pthread_t id;
            if (pthread_create(&id, &attr, helper_main, (void *)(uintptr_t)gen) != 0)
                break;   /* fewer helpers: the others take their parts */
            ++pool.started;
        }
        pthread_attr_destroy(&attr);
    }
    pool.job = s;
    __atomic_store_n(&pool.limit, T - 1, __ATOMIC_RELAXED);
    __atomic_store_n(&pool.word, 0, __ATOMIC_RELEASE);   /* open: job and limit are seen by who joins */
    __atomic_store_n(&pool.gen, gen + 1, __ATOMIC_SEQ_CST);
    if (__atomic_load_n(&pool.sleepers, __ATOMIC_SEQ_CST)) {
        pthread_mutex_lock(&pool.m);
        pthread_cond_broadcast(&pool.cv);
        pthread_mutex_unlock(&pool.m);
    }
    take_parts(s);
    int zero = 0;   /* close: wait for the helpers in it to finish their parts */
    while (!__atomic_compare_exchange_n(&pool.word, &zero, WORD_CLOSED, 0, __ATOMIC_ACQUIRE, __ATOMIC_RELAXED)) {
        zero = 0;
        relax();
    }
    pthread_mutex_unlock(&pool.busy);
    return s->ok;
}

/* run on rows [0, N): from 2 * thread_rows states, on up to n_threads threads (at least
 * thread_rows states a thread), this one included, taking parts until none is left */
static int run_all(const Bound *b, char **data, npy_intp N, double *res)
{
    int T = n_threads;
    if (T > 1 && N / thread_rows < T)
        T = (int)(N / thread_rows);
    if (T <= 1)
        return run(b, data, 0, N, res);
    Parts s = {b, data, res, N, 0, T, 1};
    int ok = run_pooled(&s, T);
    return ok == -2 ? run_started(&s, T) : ok;
}

static int plain(PyObject *o, int nd_lo, int nd_hi)
{
    if (!PyArray_Check(o))
        return 0;
    PyArrayObject *a = (PyArrayObject *)o;
    int nd = PyArray_NDIM(a);
    return PyArray_TYPE(a) == NPY_DOUBLE && nd >= nd_lo && nd <= nd_hi && PyArray_IS_C_CONTIGUOUS(a) &&
           PyArray_ISALIGNED(a) && !PyArray_ISBYTESWAPPED(a);
}

static PyObject *bound_call(PyObject *self, PyObject *const *args, size_t nargsf, PyObject *kwnames)
{
    Bound *b = (Bound *)self;
    Py_ssize_t nargs = PyVectorcall_NARGS(nargsf);
    if (kwnames || (nargs != b->n_in && nargs != b->n_in + 1)) {
        PyErr_Format(PyExc_TypeError, "a native kernel takes %d arrays and an optional out", b->n_in);
        return NULL;
    }
    char *data[MAX_LISTS];
    int nd = 0;
    npy_intp N = 1;
    for (int i = 0; i < b->n_in; ++i) {
        if (!plain(args[i], 1, 2))
            Py_RETURN_NONE;
        PyArrayObject *a = (PyArrayObject *)args[i];
        npy_intp *d = PyArray_DIMS(a);
        int ndi = PyArray_NDIM(a);
        if (d[ndi - 1] != b->width[i])
            Py_RETURN_NONE;
        if (i == 0) {
            nd = ndi;
            N = ndi == 2 ? d[0] : 1;
        } else if (ndi != nd || (nd == 2 && d[0] != N)) {
            Py_RETURN_NONE;
        }
        data[i] = PyArray_BYTES(a);
    }
    /* a non-finite input the result does not depend on (a Jacobian's joints off its link's path)
     * would pass the result's test: the full path names it */
    for (int i = 0; i < b->n_in; ++i)
        if (!all_finite((const double *)data[i], N * b->width[i]))
            Py_RETURN_NONE;
    int lead = nd == 2;
    PyObject *out = nargs > b->n_in ? args[b->n_in] : Py_None;
    if (out != Py_None) {
        if (!plain(out, lead + b->out_nd, lead + b->out_nd) || !PyArray_ISWRITEABLE((PyArrayObject *)out))
            Py_RETURN_NONE;
        npy_intp *d = PyArray_DIMS((PyArrayObject *)out);
        if ((lead && d[0] != N) || d[lead] != b->out_dims[0] || (b->out_nd == 2 && d[lead + 1] != b->out_dims[1]))
            Py_RETURN_NONE;
        if (lead) {   /* a batch writes state by state: out may be an input only row for row */
            char *o = PyArray_BYTES((PyArrayObject *)out);
            size_t on = sizeof(double) * (size_t)N * (size_t)b->n_res;
            for (int i = 0; i < b->n_in; ++i) {
                size_t in_n = sizeof(double) * (size_t)N * (size_t)b->width[i];
                if (data[i] < o + on && o < data[i] + in_n && (data[i] != o || b->width[i] != b->n_res))
                    Py_RETURN_NONE;   /* the full path computes, then writes */
            }
        }
        Py_INCREF(out);
    } else {
        npy_intp dims[3] = {N, b->out_dims[0], b->out_dims[1]};
        out = PyArray_SimpleNew(lead + b->out_nd, lead ? dims : dims + 1, NPY_DOUBLE);
        if (!out)
            return NULL;
    }
    int ok;
    double *res = (double *)PyArray_DATA((PyArrayObject *)out);
    if (N >= b->gil_rows) {
        Py_BEGIN_ALLOW_THREADS
        ok = run_all(b, data, N, res);
        Py_END_ALLOW_THREADS
    } else {
        ok = run(b, data, 0, N, res);
    }
    if (ok < 0) {
        Py_DECREF(out);
        return PyErr_NoMemory();
    }
    if (!ok) {
        Py_DECREF(out);
        Py_RETURN_NONE;
    }
    return out;
}

static void bound_dealloc(PyObject *self)
{
    Py_XDECREF(((Bound *)self)->keep);
    Py_TYPE(self)->tp_free(self);
}

static PyTypeObject BoundType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "lie_dynamics_native.Bound",
    .tp_basicsize = sizeof(Bound),
    .tp_dealloc = bound_dealloc,
    .tp_vectorcall_offset = offsetof(Bound, vectorcall),
    .tp_call = PyVectorcall_Call,
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_VECTORCALL,
    .tp_doc = "A native kernel with its parameters bound: call(*per_state_arrays[, out])",
};

/* bind(address, lanes address, lanes, sincos, widths, params, n_out, n_res, out_dims, check, rtol, gil_rows,
 * keep); sincos: (list, position) pairs of the inputs whose sin and cos the form across states takes */
static PyObject *bind(PyObject *mod, PyObject *args)
{
    unsigned long long addr, lanes_addr;
    int lanes;
    PyObject *sincos, *widths, *params, *dims, *keep;
    Py_ssize_t n_out, n_res, gil_rows;
    int check;
    double rtol;
    if (!PyArg_ParseTuple(args, "KKiO!O!O!nnO!idnO", &addr, &lanes_addr, &lanes, &PyTuple_Type, &sincos, &PyTuple_Type,
                          &widths, &PyTuple_Type, &params, &n_out, &n_res, &PyTuple_Type, &dims, &check, &rtol, &gil_rows,
                          &keep))
        return NULL;
    Py_ssize_t n_in = PyTuple_GET_SIZE(widths), n_par = PyTuple_GET_SIZE(params), out_nd = PyTuple_GET_SIZE(dims);
    if (n_in < 1 || n_in > MAX_LISTS || n_par > MAX_LISTS || out_nd < 1 || out_nd > 2) {
        PyErr_SetString(PyExc_ValueError, "bind: unsupported kernel signature");
        return NULL;
    }
    Bound *b = PyObject_New(Bound, &BoundType);
    if (!b)
        return NULL;
    b->vectorcall = bound_call;
    b->fn = (kernel_fn)(uintptr_t)addr;
    b->lanes_fn = lanes_addr && lanes > 1 && lanes <= 64 ? (lanes_kernel_fn)(uintptr_t)lanes_addr : NULL;
    b->lanes = b->lanes_fn ? lanes : 1;
    b->n_in = (int)n_in;
    b->n_par = (int)n_par;
    b->out_nd = (int)out_nd;
    b->out_dims[1] = 1;
    for (Py_ssize_t i = 0; i < out_nd; ++i)
        b->out_dims[i] = PyLong_AsSsize_t(PyTuple_GET_ITEM(dims, i));
    for (Py_ssize_t i = 0; i < n_in; ++i)
        b->width[i] = PyLong_AsSsize_t(PyTuple_GET_ITEM(widths, i));
    Py_ssize_t n_sc = PyTuple_GET_SIZE(sincos) / 2;
    b->n_sc = 0;
    for (Py_ssize_t j = 0; j < n_sc && j < MAX_SINCOS; ++j) {
        long list = PyLong_AsLong(PyTuple_GET_ITEM(sincos, 2 * j));
        Py_ssize_t pos = PyLong_AsSsize_t(PyTuple_GET_ITEM(sincos, 2 * j + 1));
        if (list < 0 || list >= n_in || pos < 0 || pos >= b->width[list])
            break;
        b->sc_list[j] = (int)list;
        b->sc_pos[j] = pos;
        b->n_sc = (int)j + 1;
    }
    if (b->n_sc != n_sc)   /* a table this call path cannot follow: state by state */
        b->lanes_fn = NULL, b->lanes = 1;
    for (Py_ssize_t i = 0; i < n_par; ++i) {
        PyObject *p = PyTuple_GET_ITEM(params, i);
        if (!plain(p, 1, 1)) {
            b->keep = NULL;
            Py_DECREF(b);
            PyErr_SetString(PyExc_ValueError, "bind: parameters must be contiguous float64 vectors");
            return NULL;
        }
        b->par[i] = (const double *)PyArray_DATA((PyArrayObject *)p);
    }
    b->n_out = n_out;
    b->n_res = n_res;
    b->check = check;
    b->rtol = rtol;
    b->gil_rows = gil_rows;
    Py_INCREF(keep);
    b->keep = keep;
    if (PyErr_Occurred()) {
        Py_DECREF(b);
        return NULL;
    }
    return (PyObject *)b;
}


#include "native_method.c"   /* Method: a Model method that runs its kernel from C */
#include "native_command.c"  /* Command: the dynamics node's fused command path */

/* set_threads(n, min_rows) -> the previous n */
static PyObject *set_threads(PyObject *mod, PyObject *args)
{
    int n;
    Py_ssize_t rows;
    if (!PyArg_ParseTuple(args, "in", &n, &rows))
        return NULL;
    if (n < 1 || n > 64 || rows < 1) {
        PyErr_SetString(PyExc_ValueError, "set_threads: n from 1 to 64, min_rows >= 1");
        return NULL;
    }
    int old = n_threads;
    n_threads = n;
    thread_rows = rows;
    return PyLong_FromLong(old);
}

/* sincos_batch(x, grouped) -> (sin, cos) of a contiguous float64 vector, in x's order or grouped
 * as a batch computes them (bench/probes/batch_sincos.py times both; the values are the same) */
static PyObject *sincos_batch(PyObject *mod, PyObject *args)
{
    PyObject *xo;
    int grouped;
    if (!PyArg_ParseTuple(args, "Op", &xo, &grouped))
        return NULL;
    if (!plain(xo, 1, 1)) {
        PyErr_SetString(PyExc_ValueError, "sincos_batch: a contiguous float64 vector");
        return NULL;
    }
    npy_intp n = PyArray_DIM((PyArrayObject *)xo, 0);
    const double *x = (const double *)PyArray_DATA((PyArrayObject *)xo);
    PyObject *so = PyArray_SimpleNew(1, &n, NPY_DOUBLE), *co = PyArray_SimpleNew(1, &n, NPY_DOUBLE);
    unsigned char *key = PyMem_Malloc(n + 1);
    int *order = PyMem_Malloc(sizeof(int) * (n + 1));
    if (!so || !co || !key || !order) {
        Py_XDECREF(so);
        Py_XDECREF(co);
        PyMem_Free(key);
        PyMem_Free(order);
        return PyErr_NoMemory();
    }
    double *s = (double *)PyArray_DATA((PyArrayObject *)so), *c = (double *)PyArray_DATA((PyArrayObject *)co);
    Py_BEGIN_ALLOW_THREADS
    if (grouped) {
        for (npy_intp k = 0; k < n; k += SC_CHUNK * 7)   /* as run() on a 7-joint arm */
            sincos_grouped(x + k, n - k < SC_CHUNK * 7 ? n - k : SC_CHUNK * 7, s + k, c + k, key, order);
    } else {
        for (npy_intp i = 0; i < n; ++i) {
            double si, ci;
            sincos1(x[i], &si, &ci);
            s[i] = si;
            c[i] = ci;
        }
    }
    Py_END_ALLOW_THREADS
    PyMem_Free(key);
    PyMem_Free(order);
    return Py_BuildValue("NN", so, co);
}

static PyMethodDef methods[] = {
    {"bind", bind, METH_VARARGS, "Bind a kernel's address and parameters (native.py)."},
    {"set_threads", set_threads, METH_VARARGS, "Threads of the native batches (native.set_threads)."},
    {"sincos_batch", sincos_batch, METH_VARARGS, "sin and cos of a vector, in order or grouped as batches do."},
    {"method", method_new, METH_VARARGS, "A Model method that runs its native kernel first (dispatch.native_first)."},
    {"invalidate", invalidate, METH_NOARGS, "Every Method resolves its kernel again."},
    {"command_path", command_path, METH_VARARGS, "The dynamics node's fused command path (ros/core/fused.py)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "lie_dynamics_native", NULL, -1, methods};

PyMODINIT_FUNC PyInit_lie_dynamics_native(void)
{
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
    __builtin_cpu_init();
    has_avx = __builtin_cpu_supports("avx");
#endif
    import_array();
    import_umath();
    if (pthread_atfork(NULL, NULL, pool_after_fork) != 0) {
        PyErr_SetString(PyExc_RuntimeError, "pthread_atfork failed");
        return NULL;
    }
    if (PyType_Ready(&BoundType) < 0 || PyType_Ready(&MethodType) < 0 || PyType_Ready(&CommandType) < 0)
        return NULL;
    str_version = PyUnicode_InternFromString("version");
    str_out = PyUnicode_InternFromString("out");
    if (!str_version || !str_out)
        return NULL;
    return PyModule_Create(&module);
}
