"""Running the generated kernels: one cache, one threshold table, one dispatch, one batch runner.

Compiled code depends only on a model's structure (home poses, screws, tree, mimic map), so
it is cached by a fingerprint of that structure in one bounded LRU shared by all models:
copies of a model, and models loaded from the same URDF, share their kernels. What changes
at run time (inertias and payloads, gravity, locked-joint values) enters the kernels as
parameter lists, cached per model until the model's version changes (every setter bumps it).

A kernel is described by a `Spec` (its traced form lives in codegen/traced/): how to build
it from the model's Frames, which parameter lists follow the per-state arguments, which
entry of THRESHOLDS says when it runs and how its outputs are accepted; per structure it is
one kernel.Kernel. `route` is the one dispatch decision: the float kernel (one state, or a
small batch state by state), the kernel on numpy rows (a large batch), or None: the
algorithm's vectorised reference. Every algorithm entry point runs `fast` (the call as
given), then, when it declines, Model.validate once and `run` (native, route, kernel,
accept), then its reference. A thread inside `deferred` (a control path) never builds kernel
code: until another thread has built it (`build`), its calls take the reference.
"""
import collections
import contextlib
import hashlib
import threading
import weakref

import numpy as np

from . import native as _native
from .thresholds import THRESHOLDS
from .frames import Frames
from .kernel import Kernel, builds as _kernel_builds


def pairs(model):
    """(body, ancestor-or-self) pairs: the sum of the body depths (the regressor's size)."""
    return structural(model, 'pairs', lambda: int(model.depth.sum()))


def route(model, name, N=None):
    """The one dispatch decision for THRESHOLDS[name] and N states (None: one state):
    'loop' (the float kernel, state by state), 'rows' (numpy rows) or None (vectorised)."""
    t = THRESHOLDS[name]
    size = model.nb if t.size == 'bodies' else pairs(model)
    if size > t.compile_max:
        return None
    if N is None or N < t.loop_below:
        return 'loop' if size <= t.float_max else None
    rows_from = t.rows_from if t.large is None or size <= t.large else t.rows_from_large
    return 'rows' if N >= rows_from else None


# ---------------------------------------------------------------------------- caches
class _Slot:
    """What the runtime keeps for one live model (dropped with it): its fingerprint, Frames and
    kernels (structure, never invalidated) and values that follow the model's version."""
    __slots__ = ('ref', 'version', 'fingerprint', 'frames', 'kernels', 'structure', 'values', 'fast', 'natives')

    def __init__(self, model):
        self.ref = weakref.ref(model)
        self.version, self.fingerprint, self.frames = None, None, None
        self.kernels, self.structure, self.values, self.fast, self.natives = {}, {}, {}, {}, {}


_SLOTS = {}                                   # id(model) -> _Slot, removed when the model dies
_SHARED = collections.OrderedDict()           # (fingerprint, name) -> kernel or Frames, LRU
_LOCK = threading.Lock()
_BUILDS = [0]


def _slot(model):
    s = _SLOTS.get(id(model))
    if s is None or s.ref() is not model:
        s = _SLOTS[id(model)] = _Slot(model)
        weakref.finalize(model, _SLOTS.pop, id(model), None)
    if s.version != model.version:
        s.values, s.fast, s.natives = {}, {}, {}   # new dicts: concurrent readers keep the old ones
        s.version = model.version
    return s


def _shared(key, make):
    """The LRU entry `key`, made on a miss (outside the lock: builds take long); `_BUILDS`
    counts the Frames made (kernels count their renderings: kernel.builds)."""
    with _LOCK:
        v = _SHARED.get(key)
        if v is not None:
            _SHARED.move_to_end(key)
            return v
    v = make()
    with _LOCK:
        _BUILDS[0] += isinstance(v, Frames)
        v = _SHARED.setdefault(key, v)
        while len(_SHARED) > THRESHOLDS['compiled_cache']:
            _SHARED.popitem(last=False)
    return v


def cache_info():
    """dict(builds=kernels rendered and Frames built since the process started, cached=entries
    in the shared cache, models=live models with runtime state)."""
    return dict(builds=_BUILDS[0] + _kernel_builds(), cached=len(_SHARED), models=len(_SLOTS))


def clear():
    """Forget every compiled kernel and cached value (live models rebuild on next use)."""
    with _LOCK:
        _SHARED.clear()
    _SLOTS.clear()


def derived(model, key, compute):
    """compute(), cached for the model until its version changes (a setter ran)."""
    s = _slot(model)
    v = s.values.get(key)
    if v is None:
        v = s.values[key] = compute()
    return v


def structural(model, key, compute):
    """compute(), cached for the model's lifetime (it may only depend on the structure)."""
    s = _slot(model)
    v = s.structure.get(key)
    if v is None:
        v = s.structure[key] = compute()
    return v


def fingerprint(model):
    """Hash of everything a kernel's source depends on (copies of a model share kernels)."""
    s = _slot(model)
    if s.fingerprint is None:
        h = hashlib.sha1()
        for a in (model.M, model.S, model.parent, model.E, model.L != 0, model.c0 != 0):
            h.update(np.ascontiguousarray(a).tobytes())
            h.update(str(np.shape(a)).encode())
        s.fingerprint = h.hexdigest()
    return s.fingerprint


def frames(model):
    """The model's Frames (shared by models of the same structure)."""
    s = _slot(model)
    if s.frames is None:
        s.frames = _shared((fingerprint(model), 'frames'), lambda: Frames(model))
    return s.frames


def _entry(model, spec):
    """spec's Kernel of this model's structure (created, not traced: kernel.Kernel), or None:
    too large for THRESHOLDS, spec.supports(model) false, or screws other than unit revolute
    / prismatic axes."""
    s = _slot(model)
    k = s.kernels.get(spec.name)
    if k is None:
        t = THRESHOLDS[spec.limits]
        if (model.nb if t.size == 'bodies' else pairs(model)) > t.compile_max \
                or (spec.supports is not None and not spec.supports(model)) or not frames(model).supported:
            k = False
        else:
            fr, fp = frames(model), fingerprint(model)
            k = _shared((fp, spec.name), lambda: Kernel(lambda: spec.build(fr), spec.name, fr, fp))
        s.kernels[spec.name] = k
    return k or None


# ---------------------------------------------------------------------------- deferred builds
_DEFER = threading.local()


class deferred:
    """`with deferred(request):` this thread builds no kernel code: a call whose kernel is not
    built yet (its C library not loaded, its Python forms not made) takes the algorithm's
    reference path, and request(model, spec) asks for the build, which `build` does in another
    thread. For a control path: generating and compiling a kernel takes up to seconds, the
    reference answers at once. One instance may be entered again, by any thread (a class, not a
    generator: a control path enters it per message, in about a tenth of a microsecond)."""
    __slots__ = ('request',)

    def __init__(self, request):
        self.request = request

    def __enter__(self):
        stack = getattr(_DEFER, 'stack', None)
        if stack is None:
            stack = _DEFER.stack = []
        stack.append(getattr(_DEFER, 'request', None))
        _DEFER.request = self.request
        return self

    def __exit__(self, *exc):
        _DEFER.request = _DEFER.stack.pop()
        return False


def _native_on(model):
    return _native.wanted() and not _slot(model).structure.get('native_off')


def _later(model, spec, python=True):
    """True when this thread defers builds (`deferred`) and spec's kernel for this model is not
    built (python False: its C library only); its build is then requested."""
    request = getattr(_DEFER, 'request', None)
    if request is None:
        return False
    k = _entry(model, spec)
    if k is None or k.built(_native_on(model), python):
        return False
    request(model, spec)
    return True


def build(model, spec):
    """Build spec's kernel code for this model (what a deferred call requested): its C library
    where the native backend works, else its Python forms."""
    k = _entry(model, spec)
    if k is not None and not (_native_on(model) and k.native()):
        k.python()


# ---------------------------------------------------------------------------- parameters
def _inertia(model, fr):
    return tuple(fr.inertia_params(model.J))


def _subtree(model, fr):
    return tuple(fr.subtree_params(model.J).ravel().tolist())


def _gravity(model, fr):
    """-g: the linear part of the base acceleration (0, -g)."""
    return tuple(model.base_acceleration[3:].tolist())


def _offsets(model, fr):
    return tuple(fr.offsets(model.e0))


PARAMETERS = {'inertia': _inertia, 'subtree': _subtree, 'gravity': _gravity, 'offsets': _offsets,
              'no_gravity': lambda model, fr: (0.0, 0.0, 0.0)}


def parameter(model, kind):
    """One parameter list of the kernels, in the primed frames (codegen.frames), cached until
    the model's version changes: 'inertia' (10 per body), 'subtree' (gravity kernel, 4 per
    body), 'gravity' (-g), 'no_gravity' (zeros) or 'offsets' (body offsets of locked and
    offset joints)."""
    return derived(model, kind, lambda: PARAMETERS[kind](model, frames(model)))


def as_rows(values):
    """Parameter lists as 0-d arrays, for the rows kernels: a ufunc takes a 0-d array operand
    ~0.25 us faster than a Python float (no scalar conversion per call)."""
    return tuple(tuple(np.array(v) for v in vs) for vs in values)


# ---------------------------------------------------------------------------- kernels
class Spec:
    """A generated kernel: `name` (its cache key: specs of one name share the compiled code),
    `build(frames)` -> its kernel.Trace or None, `params` (the parameter lists that follow
    its per-state arguments, the trace's Params lists in order: PARAMETERS keys, or
    functions (model) -> tuple), `limits` (its THRESHOLDS entry), `supports` (an extra
    condition on the model, or None), `rows_arrays` (parameters of the rows form as 0-d
    arrays, see as_rows), `checked` (the outputs are checked: the rows form runs without
    floating-point warnings), `pooled` (the batch runner keeps its register blocks between
    calls: run_rows), `rows_chunk` (None, or the THRESHOLDS entry bounding the states of one
    rows call) and `result` (model) -> (shape of one state's result, rtol): its first
    prod(shape) values are the result; rtol None, or the outputs after them are pivots then
    their scales, as many each, accepted above rtol times the scale (`accepts`). None: all
    outputs as a vector."""
    __slots__ = ('name', 'build', 'params', 'limits', 'supports', 'rows_arrays', 'checked', 'pooled', 'result',
                 'rows_chunk')

    def __init__(self, name, build, params, limits, supports=None, rows_arrays=False, checked=False,
                 pooled=False, result=None, rows_chunk=None):
        self.name, self.build, self.params, self.limits = name, build, tuple(params), limits
        self.supports, self.rows_arrays, self.checked, self.pooled = supports, rows_arrays, checked, pooled
        self.result, self.rows_chunk = result, rows_chunk

    def variant(self, params):
        """The same kernel with other parameter lists (e.g. gravity switched off)."""
        return Spec(self.name, self.build, params, self.limits, self.supports, self.rows_arrays, self.checked,
                    self.pooled, self.result, self.rows_chunk)


def kernel(model, spec):
    """spec's Kernel for this model with its Python forms built, or None: too large for
    THRESHOLDS, screws other than unit revolute / prismatic axes, or spec.supports(model)
    false."""
    k = _entry(model, spec)
    return k if k is not None and k.python() else None


class Bound:
    """spec's Kernel with the parameter lists of one model version: `kernel`, `function` (its
    float function), `params` and `rows_params` (those of the rows form)."""
    __slots__ = ('kernel', 'function', 'params', 'rows_params')

    def __init__(self, k, params, rows_params):
        self.kernel, self.function, self.params, self.rows_params = k, k.function, params, rows_params


def _parameters(model, spec):
    return tuple(parameter(model, p) if isinstance(p, str) else p(model) for p in spec.params)


def _bind(s, model, spec):
    """The Bound of spec for the model's version, or False (no kernel)."""
    b = s.values.get(spec)
    if b is None:
        k = kernel(model, spec)
        b = False
        if k:
            P = _parameters(model, spec)
            if len(P) != k.roles.count('param'):
                raise ValueError(f'kernel {spec.name}: {len(P)} parameter lists for {k.roles.count("param")}')
            b = Bound(k, P, as_rows(P) if spec.rows_arrays else P)
        s.values[spec] = b
    return b


def params(model, spec, rows=False):
    """The parameter lists of spec's kernel (for its rows form when rows), cached until the
    model's version changes; None when the model has no such kernel."""
    b = _bind(_slot(model), model, spec)
    return (b.rows_params if rows else b.params) if b else None


def _result(model, spec, n_out):
    """(shape of one state's result, its number of values, rtol or None): spec.result."""
    shape, rtol = spec.result(model) if spec.result else ((n_out,), None)
    return tuple(shape), int(np.prod(shape)), rtol


def accepts(vals, m, rtol):
    """Outputs of a kernel with pivots (Spec.result) for one state (a sequence) or a batch
    (N, k): a finite result (the first m) and every pivot above rtol times its scale (the
    outputs after the result: pivots, then as many scales). The one acceptance rule of the
    Python kernels (native_call.c applies it to the C kernels' outputs)."""
    if isinstance(vals, np.ndarray):
        p = (vals.shape[1] - m) // 2
        return bool(np.all(np.isfinite(vals[:, :m])) and np.all(vals[:, m:m + p] > rtol * vals[:, m + p:]))
    p = (len(vals) - m) // 2
    s = sum(vals[:m])
    return s - s == 0.0 and all(d > rtol * c for d, c in zip(vals[m:m + p], vals[m + p:], strict=True))


# ---------------------------------------------------------------------------- one call's fast path
def _declined(*args):
    return None


class _Single:
    """`fast` without a native kernel: one state given as (k,) float64 arrays or sequences of
    k numbers (k per argument list) with a finite sum, through the float kernel; None for
    anything else, `out` given, a kernel that raised or outputs that fail `accepts`."""
    __slots__ = ('function', 'params', 'widths', 'n_state', 'shape', 'm', 'rtol', 'packer', 'size', 'kind')

    def __init__(self, model, spec, b):
        k = b.kernel
        self.function, self.params, self.widths, self.n_state = b.function, b.params, k.widths, k.n_state
        self.shape, self.m, self.rtol = _result(model, spec, k.n_out)
        self.packer, self.size = k.packer, (k.scatter[1] if k.scatter else None)
        # what becomes of the outputs: 0 all as a vector, 1 a matrix, 2 scattered, 3 pivots to test
        self.kind = 2 if k.packer else 3 if self.rtol is not None else 1 if len(self.shape) > 1 else 0

    def __call__(self, *args):
        ns = self.n_state
        if len(args) != ns and (len(args) != ns + 1 or args[ns] is not None):
            return None
        lists = _float_lists(self.widths, args, ns)
        if lists is None:
            return None
        try:
            vals = self.function(*lists, *self.params)
        except (ValueError, ZeroDivisionError, OverflowError):   # sqrt of a negative pivot, a zero pivot
            return None
        kind = self.kind
        if kind == 0:
            return np.array(vals)
        if kind == 1:
            return np.fromiter(vals, float, self.m).reshape(self.shape)
        if kind == 2:
            out = np.empty(self.size)
            self.packer.pack_into(out, 0, *vals)
            return out.reshape(self.shape)
        if not accepts(vals, self.m, self.rtol):
            return None
        return np.fromiter(vals, float, self.m).reshape(self.shape)


def _float_lists(widths, xs, count):
    """Float lists of the first `count` of one state's arguments xs: (k,) float64 arrays or
    sequences of k numbers, k from widths, whose sum is finite; else None (the caller then
    validates in full)."""
    out = []
    s = 0.0
    for i in range(count):
        x = xs[i]
        n = widths[i]
        if type(x) is _ND:
            if x.shape != (n,) or x.dtype != _F64:
                return None
            x = x.tolist()
        elif type(x) in (list, tuple) and len(x) == n:
            try:
                x = [float(v) for v in x]
            except (TypeError, ValueError):
                return None
        else:
            return None
        s += sum(x)
        out.append(x)
    return out if s - s == 0.0 else None   # inf - inf and nan are not 0: exact checks


def fast(model, spec):
    """The first step of every entry point: a callable taking one call's per-state arguments
    as given (and an optional `out`), unvalidated, that returns spec's result (shape of
    Spec.result; (N,) + shape for a batch) or None, and then the caller validates and takes
    the full path (`run`). It is the native kernel (runtime.native: contiguous float64 (n,)
    or (N, n) arrays, the result checked in C), else, for one state that route sends to the
    float kernel, that kernel on the float lists, else a callable that always declines.
    Cached until the model's version changes."""
    s = _SLOTS.get(id(model))   # the hot path of a control loop: _slot, inlined
    if s is None or s.version != model.version or s.ref() is not model:
        s = _slot(model)
    f = s.fast.get(spec)
    if f is None:
        if _later(model, spec):   # not kept: it may be built by the next call
            return _declined
        f = native(model, spec)
        if f is None:
            b = _bind(s, model, spec) if route(model, spec.limits) == 'loop' else False
            f = _Single(model, spec, b) if b else _declined
        s.fast[spec] = f
    return f


def native(model, spec):
    """spec's kernel compiled to C with this model's parameters bound (native.bind): call it
    with the per-state arrays (n,) or (N, n) and an optional `out`; it returns the result or
    None (input not contiguous float64 of the right shapes, or a result that is not finite
    or fails the pivot test: the caller's full path takes over). None when the model has no
    native kernel (backend off or unavailable, too large, unsupported). Cached until the
    model's version changes."""
    s = _SLOTS.get(id(model))   # the hot path of a control loop: _slot, inlined
    if s is None or s.version != model.version or s.ref() is not model:
        s = _slot(model)
    b = s.natives.get(spec)
    if b is None:
        if _later(model, spec, python=False):
            return None
        b = s.natives[spec] = _bind_native(model, spec) or False
    return b or None


def use_native(model, on=True):
    """Let this model use the native kernels (the default) or only the Python ones (on=False:
    for comparisons in one process; LIE_DYNAMICS_NATIVE=0 switches them off everywhere)."""
    s = _slot(model)
    s.structure['native_off'] = not on
    s.natives, s.fast, s.values = {}, {}, {}   # values: derived entries that hold a bound native kernel


def _bind_native(model, spec):
    if _slot(model).structure.get('native_off') or not _native.wanted():
        return None
    k = _entry(model, spec)
    lib = k.native() if k is not None else None
    if lib is None:
        return None
    try:
        P = _parameters(model, spec)
    except (ValueError, ZeroDivisionError, OverflowError):
        return None
    if tuple(len(p) for p in P) != lib.par_lengths:
        return None
    shape, m, rtol = _result(model, spec, lib.n_out)
    return _native.bind(lib, P, m, shape, rtol is not None, rtol or 0.0, THRESHOLDS['native_gil_rows'])


def forget(model):
    """Drop what the runtime keeps for this model (e.g. after changing THRESHOLDS); its
    kernels come back from the shared cache."""
    _SLOTS.pop(id(model), None)


# ---------------------------------------------------------------------------- the full path
def evaluate(model, spec, arrays, mode, out=None):
    """spec's kernel on validated per-state arrays (N, k_i), in the kernel's order: 'loop'
    (floats, state by state) or 'rows' (into `out` when given). Returns its outputs (N,
    n_out), or None when the model has no such kernel or the float kernel raised (sqrt of a
    negative pivot, a zero pivot: callers report it by the reference)."""
    b = _bind(_slot(model), model, spec)
    return _evaluate(b, spec, arrays, mode, out) if b else None


def _evaluate(b, spec, arrays, mode, out=None):
    k = b.kernel
    try:
        if mode == 'loop':
            return np.array(run_loop(b.function, arrays, b.params), dtype=float).reshape(len(arrays[0]), k.n_out)
        return run_rows(k, list(arrays) + list(b.rows_params), out=out, quiet=spec.checked, pooled=spec.pooled)
    except (ValueError, ZeroDivisionError, OverflowError):   # also from parameters alone, as floats
        return None


def run(model, spec, arrays, mode=None, native_first=True, c_order=False):
    """The full path after validation: spec's kernel on validated (N, k_i) per-state arrays,
    in the kernel's order. Its C form first (mode None and native_first), else the float
    ('loop') or rows kernel where route (or the forced mode) says so, its outputs accepted
    as Spec.result says and scattered into place (Kernel.scatter). Returns (N, values of one
    state's result); c_order: the rows kernel writes a C-ordered array (else it returns the
    transpose of a state-last one). None: no kernel, the vectorised reference is faster, or
    the outputs failed the check (the reference then reports it), or a build this thread defers."""
    N = len(arrays[0])
    if _later(model, spec):
        return None
    if mode is None and native_first:
        nk = native(model, spec)
        if nk is not None:
            r = nk(*arrays)
            if r is None and not all(a.flags.c_contiguous for a in arrays):
                r = nk(*[np.ascontiguousarray(a) for a in arrays])
            if r is not None:
                return r if r.ndim == 2 else r.reshape(N, -1)
    mode = check_mode(mode) or route(model, spec.limits, N)
    b = _bind(_slot(model), model, spec) if mode else False
    if not b:
        return None
    k = b.kernel
    if k.scatter is not None:
        return _scattered(b, spec, arrays, mode)
    vals = _evaluate(b, spec, arrays, mode, np.empty((N, k.n_out)) if c_order and mode == 'rows' else None)
    if vals is None:
        return None
    _, m, rtol = _result(model, spec, k.n_out)
    if rtol is not None:
        if not accepts(vals, m, rtol):
            return None
        vals = vals[:, :m]
    return vals


def _scattered(b, spec, arrays, mode):
    """run for a kernel whose outputs are scattered into a larger result (Kernel.scatter)."""
    k = b.kernel
    idx, size = k.scatter
    N = len(arrays[0])
    if mode == 'loop':   # each state's outputs packed straight into place
        res = np.empty((N, size))
        fn, P, pack = b.function, b.params, k.packer.pack_into
        try:
            for s, state in enumerate(zip(*[a.tolist() for a in arrays], strict=True)):
                pack(res, 8 * size * s, *fn(*state, *P))
        except (ValueError, ZeroDivisionError, OverflowError):
            return None
        return res
    res = np.zeros((N, size))
    chunk = THRESHOLDS[spec.rows_chunk] if spec.rows_chunk else N
    for s in range(0, N, chunk):   # bounds the (outputs, states) work array of the batch runner
        sl = slice(s, s + chunk)
        vals = _evaluate(b, spec, [a[sl] for a in arrays], 'rows')
        if vals is None:
            return None
        res[sl, idx] = vals
    return res


def check_out(out, shape):
    """`out` when it is a writeable float64 array of this shape (or None), else ValueError."""
    if out is not None and not (isinstance(out, np.ndarray) and out.dtype == _F64 and out.shape == tuple(shape)
                                and out.flags.writeable):
        got = f'{out.dtype} array of shape {out.shape}' if isinstance(out, np.ndarray) else type(out).__name__
        raise ValueError(f'out must be a writeable float64 array of shape {tuple(shape)}, got {got}')
    return out


def deliver(result, out):
    """result, written into `out` when given (checked by check_out before the work)."""
    if out is None:
        return result
    out[...] = result
    return out


def check_mode(mode):
    """A forced mode of the kernel paths: 'loop', 'rows' or None (route decides)."""
    if mode not in (None, 'loop', 'rows'):
        raise ValueError(f"mode must be 'loop', 'rows' or None, got {mode!r}")
    return mode


# ---------------------------------------------------------------------------- running kernels
_ND = np.ndarray
_F64 = np.dtype(float)
_NO_ERRSTATE = contextlib.nullcontext()


def is_fast_single(x, n):
    """One (n,) float64 array or sequence of n numbers with a finite sum as a float list, or None."""
    lists = _float_lists((n,), (x,), 1)
    return lists[0] if lists else None


_LOOPS = {}


def run_loop(fn, arrays, params):
    """The float kernel state by state: arrays (N, k) (the per-state arguments, first in the
    kernel's order), params the parameter lists that follow them. A list of output tuples."""
    key = (len(arrays), len(params))
    loop = _LOOPS.get(key)
    if loop is None:   # the arguments spelt out: ~0.2 us per state less than fn(*r, *params)
        a = ', '.join(f'a{i}' for i in range(key[0]))
        p = ''.join(f', p{i}' for i in range(key[1]))
        rows = 'lists[0]' if key[0] == 1 else 'zip(*lists, strict=True)'
        src = (f'def loop(fn, lists, params):\n    ({p[2:]}{"," if p else ""}) = params\n'
               f'    return [fn({a}{p}) for {a} in {rows}]\n')
        ns = {}
        exec(compile(src, '<lie_dynamics run_loop>', 'exec'), ns)
        loop = _LOOPS[key] = ns['loop']
    return loop(fn, [x.tolist() for x in arrays], params)


def run_rows(k, args, chunk=None, out=None, quiet=True, pooled=False):
    """Run Kernel k's rows form on a batch: args in the kernel's order, (N, width) arrays for
    its per-state lists (Kernel.roles), then the parameter sequences. Returns (N, k.n_out): `out` when given
    (written column by column), else the transpose of a state-last array. quiet: no
    floating-point warnings (for callers that check the outputs).

    States go in chunks (THRESHOLDS rows_chunk / rows_bytes), copied transposed into input
    rows of one register block; every operation writes into the block (render.emit_rows), so
    a chunk allocates nothing but its outputs. When `pooled`, blocks are reused across calls
    from a pool per kernel (concurrent callers never share one; later calls touch no fresh
    pages): worth it for the cheap per-call kernels (inverse dynamics, gravity). The others
    allocate per call: a block held in a pool is never freed, so glibc never raises its mmap
    threshold above it, and every large temporary of such a call (e.g. the regressor's
    output) stays a fresh mmap with its page faults.
    """
    rows_fn = k.rows()
    lay = k.layout
    if lay is None:   # the block's height and the chunk size: fixed per kernel
        height = k.nreg + 1 + sum(k.widths[:k.n_state])
        size = int(min(THRESHOLDS['rows_chunk'], max(256, THRESHOLDS['rows_bytes'] // (8 * height))))
        lay = k.layout = (height, size)
    height, size = lay
    size = chunk or size
    regs = k.nreg + 1
    idx = range(k.n_state)
    n_out = k.n_out
    N = args[0].shape[0]
    buf = k.pool.pop() if pooled and k.pool else None
    if buf is None or buf.size < height * min(size, N):
        buf = np.empty(height * (size if pooled else min(size, N)))
    res = np.empty((n_out, N)) if out is None else None
    call = list(args)
    errs = np.errstate(all='ignore') if quiet else _NO_ERRSTATE
    try:
        with errs:
            for start in range(0, N, size):
                stop = min(N, start + size)
                view = buf[:height * (stop - start)].reshape(height, stop - start)   # adjacent rows
                r = regs
                for i in idx:
                    w = k.widths[i]
                    view[r:r + w] = args[i][start:stop].T
                    call[i] = view[r:r + w]
                    r += w
                vals = rows_fn(*call, list(view[:regs]))
                if out is None:
                    for j, v in enumerate(vals):
                        res[j, start:stop] = v
                else:
                    for j, v in enumerate(vals):
                        out[start:stop, j] = v
    finally:
        if pooled:
            k.pool.append(buf)
    return res.T if out is None else out
