"""One call of an algorithm: the fast path, one validation, the route, the kernel, acceptance.

Every algorithm's public function is two steps:

  1. the fast path, `fast(model, spec)(states..., out)`: spec's kernel on the call as given,
     unvalidated: the native kernel, or one state through the float kernel. It returns the
     result or declines (None). It is the kernel call itself, written in the public function:
     the same steps inside `call` (the arguments handed on as a tuple) measured about 0.02 us
     more per call, 2-3 % of a one-state inverse dynamics, and the fast path adds nothing;
  2. when it declines, `call(model, entry, states, out, extra)`: validate once (Model.validate,
     lie_dynamics.validation), check `out` (`check_out`), then entry.full(model, arrays,
     *extra) on the validated (N, n) arrays: `run` (the native kernel, else the float or rows
     kernel where `route` says so, its outputs accepted as the Spec's Result says), else the
     algorithm's vectorised reference, which reports what the kernels declined; then deliver.
     Internal fallbacks call such validated functions, never a public function.

Model.inverse_dynamics, gravity, mass_matrix, forward_dynamics and the two derivative families
take one step less: `native_first` makes them C method descriptors (native_call.c Method) that
call the model's bound native kernel from C for the plain call (the per-state arrays and `out=`
where the method has it), and the Python method otherwise.
Model.jacobian and Model.jacobian_dot_times_qd do the same through `native_keyed`, their
kernel looked up in C by the link and frame.
"""
import enum
import functools
from typing import Callable, NamedTuple

import numpy as np

from . import native as _native
from .batch import run_loop, run_rows
from .cache import SLOTS, entry as _kernel_entry, later, size as _size, slot
from .spec import Spec, accepts, bind, parameters, result_of
from .thresholds import THRESHOLDS
from ..validation import float_lists

_F64 = np.dtype(float)
# SLOTS.get bound once: the compiler calls a method of an imported name through a new bound
# method object each time (about 40 ns more per call than the old module-level dict had)
_slot_of = SLOTS.get


def route(model, name, N=None):
    """The one dispatch decision for THRESHOLDS[name] and N states (None: one state):
    'loop' (the float kernel, state by state), 'rows' (numpy rows) or None (vectorised)."""
    t = THRESHOLDS[name]
    size = _size(model, t)
    if size > t.compile_max:
        return None
    if N is None or N < t.loop_below:
        return 'loop' if size <= t.float_max else None
    rows_from = t.rows_from if t.large is None or size <= t.large else t.rows_from_large
    return 'rows' if N >= rows_from else None


class Entry(NamedTuple):
    """An algorithm's public function as `call` runs it after the fast path: `names` (its per-state arguments, as
    messages name them), `shape` ((model) -> the shape of one state's result, for `out`; None
    for a function without `out`) and `full` ((model, arrays, *extra) -> (N,) + shape: the
    kernel by `run`, else the reference, on validated (N, n) arrays)."""
    names: tuple
    shape: Callable
    full: Callable


def call(model, entry, args, out=None, extra=()):
    """An algorithm's public function after its fast path declined (module docstring): validate
    the per-state arguments `args` once, check `out`, entry.full(model, arrays, *extra) on the
    validated arrays, deliver (one state's result, or the batch; into `out` when given). None
    when entry.full returns None (a forced kernel path the model has not: frame Jacobians)."""
    arrays, single = model.validate(entry.names, args)
    if out is not None:
        shape = tuple(entry.shape(model))
        check_out(out, shape if single else (len(arrays[0]),) + shape)
    r = entry.full(model, arrays, *extra)
    if r is None:
        return None
    return deliver(r[0] if single else r, out)


# ---------------------------------------------------------------------------- one call's fast path
def _declined(*args):
    return None


class Output(enum.Enum):
    """What becomes of a float kernel's outputs for one state (_Single)."""
    VECTOR = 'all outputs as a vector'
    MATRIX = 'the outputs reshaped'
    SCATTERED = 'packed into place in a larger result (Kernel.packer)'
    PIVOTED = 'the result, returned only when it passes accepts'


_VECTOR, _MATRIX, _SCATTERED = Output.VECTOR, Output.MATRIX, Output.SCATTERED


class _Single:
    """`fast` without a native kernel: one state given as (k,) float64 arrays or sequences of
    k numbers (k per argument list) with a finite sum, through the float kernel; None for
    anything else, `out` given, a kernel that raised or outputs that fail `accepts`."""
    __slots__ = ('function', 'params', 'widths', 'n_state', 'shape', 'm', 'rtol', 'packer', 'size', 'kind')

    def __init__(self, b):
        k = b.kernel
        self.function, self.params, self.widths, self.n_state = b.function, b.params, k.widths, k.n_state
        self.shape, self.m, self.rtol = b.result
        self.packer, self.size = k.packer, (k.scatter[1] if k.scatter else None)
        self.kind = (Output.SCATTERED if k.packer else Output.PIVOTED if self.rtol is not None
                     else Output.MATRIX if len(self.shape) > 1 else Output.VECTOR)

    def __call__(self, *args):
        ns = self.n_state
        if len(args) != ns and (len(args) != ns + 1 or args[ns] is not None):
            return None
        lists = float_lists(self.widths, args, ns)
        if lists is None:
            return None
        try:
            vals = self.function(*lists, *self.params)
        except (ValueError, ZeroDivisionError, OverflowError):   # sqrt of a negative pivot, a zero pivot
            return None
        kind = self.kind
        if kind is _VECTOR:
            return np.array(vals)
        if kind is _MATRIX:
            return np.fromiter(vals, float, self.m).reshape(self.shape)
        if kind is _SCATTERED:
            out = np.empty(self.size)
            self.packer.pack_into(out, 0, *vals)
            return out.reshape(self.shape)
        if not accepts(vals, self.m, self.rtol):
            return None
        return np.fromiter(vals, float, self.m).reshape(self.shape)


def _fast(model, spec, s):
    f = s.fast.get(spec)
    if f is None:
        if later(model, spec):   # not kept: it may be built by the next call
            return _declined
        f = native(model, spec)
        if f is None:
            b = bind(s, model, spec) if route(model, spec.limits) == 'loop' else False
            f = _Single(b) if b else _declined
        s.fast[spec] = f
    return f


def fast(model, spec):
    """The first step of every entry point: a callable taking one call's per-state arguments
    as given (and an optional `out`), unvalidated, that returns spec's result (shape of
    Spec.result; (N,) + shape for a batch) or None, and then the caller validates and takes
    the full path (`run`). It is the native kernel (`native`: contiguous float64 (n,) or
    (N, n) arrays, the result checked in C), else, for one state that route sends to the
    float kernel, that kernel on the float lists, else a callable that always declines.
    Cached until the model's version changes."""
    s = _slot_of(id(model))   # the hot path of a control loop: cache.slot, inlined
    if s is None or s.version != model.version or s.ref() is not model:
        s = slot(model)
    f = s.fast.get(spec)
    return f if f is not None else _fast(model, spec, s)


def native(model, spec):
    """spec's kernel compiled to C with this model's parameters bound (native.bind): call it
    with the per-state arrays (n,) or (N, n) and an optional `out`; it returns the result or
    None (input not contiguous float64 of the right shapes, or a result that is not finite
    or fails the pivot test: the caller's full path takes over). None when the model has no
    native kernel (backend off or unavailable, too large, unsupported). Cached until the
    model's version changes."""
    s = _slot_of(id(model))   # the hot path of a control loop: cache.slot, inlined
    if s is None or s.version != model.version or s.ref() is not model:
        s = slot(model)
    b = s.natives.get(spec)
    if b is None:
        if later(model, spec, python=False):
            return None
        b = s.natives[spec] = _bind_native(model, spec) or False
    return b or None


def _bind_native(model, spec):
    if slot(model).structure.get('native_off') or not _native.wanted():
        return None
    k = _kernel_entry(model, spec)
    lib = k.native() if k is not None else None
    if lib is None:
        return None
    try:
        P = parameters(model, spec)
    except (ValueError, ZeroDivisionError, OverflowError):
        return None
    if tuple(len(p) for p in P) != lib.par_lengths:
        return None
    return _native.bind(lib, P, result_of(model, spec, lib.n_out), THRESHOLDS['native_gil_rows'])


class native_first:
    """Decorator of a Model method whose first n_state arguments are spec's per-state arrays:
    the method becomes a C method descriptor (native_call.c Method) that runs the model's
    native kernel straight from C for model.NAME(*states) and model.NAME(*states, out=buf),
    and the Python method for every other call and whenever the kernel declines. About
    0.3 us less than the Python fast path on a one-state call (three Python frames).
    Installed on first use with the backend (built then); without it, the Python method.

    spec: a Spec, or a function (model) -> Spec for a method whose kernel depends on the model
    (forward dynamics: the looped ABA on large models). split: k > 1 for a method that returns
    k (n, n) matrices, the one kernel output (k n n,) cut as the Python method cuts it (it
    takes no out=)."""

    def __init__(self, spec, n_state, split=0):
        self.spec, self.n_state, self.split = spec, n_state, split

    def __call__(self, method):
        self.method = method
        functools.update_wrapper(self, method)
        return self

    def __set_name__(self, owner, name):
        self.owner, self.name = owner, name

    def __get__(self, obj, cls=None):
        mod = _native.module()
        if mod is None:   # asked again next time: the backend may be switched on later in the process
            return self.method.__get__(obj, cls)
        impl = self._make(mod)
        if self.owner.__dict__.get(self.name) is self:
            setattr(self.owner, self.name, impl)
        return impl.__get__(obj, cls)

    def _make(self, mod):
        return mod.method(self.method, functools.partial(_resolve, self.spec), self.n_state, False, self.split)


class native_keyed(native_first):
    """native_first for a method whose arguments after the n_state per-state arrays choose the
    kernel (a frame Jacobian's link, frame, point): kernel_of(model, *key, **kw) -> (spec, tuple
    of arrays the kernel takes after the states) or False (no kernel for these arguments: the
    Python method). The C method (native_call.c Method, keyed) resolves each key once per model
    version, so a repeated call costs a dict look-up and the kernel's own checks in C; any call
    it cannot serve (a batch, a bad argument, an unknown link) runs the Python method, which
    validates and raises."""

    def __init__(self, kernel_of, n_state):
        super().__init__(None, n_state)
        self.kernel_of = kernel_of

    def _make(self, mod):
        return mod.method(self.method, functools.partial(_resolve_keyed, self.kernel_of), self.n_state, True)


def _resolve_keyed(kernel_of, model, *key, **kw):
    """A keyed Method's kernel for this model and key: (native Bound, extras), False or None (as
    _resolve). kernel_of raising (an argument it cannot take) is the C method's slow path."""
    if not model.n:
        return False
    k = kernel_of(model, *key, **kw)
    if not k:
        return False
    r = _resolve(k[0], model)
    return (r, k[1]) if r else r


def _resolve(spec, model):
    """The Method's kernel for this model: its native Bound, False (none: cached until the
    model's version changes) or None (not now: a build deferred)."""
    if not model.n:
        return False
    if not isinstance(spec, Spec):
        spec = spec(model)
    nk = native(model, spec)
    if nk is not None:
        return nk if fast(model, spec) is nk else None
    return False if slot(model).natives.get(spec) is False or not _native.wanted() else None


# ---------------------------------------------------------------------------- the full path
def evaluate(model, spec, arrays, mode, out=None):
    """spec's kernel on validated per-state arrays (N, k_i), in the kernel's order: 'loop'
    (floats, state by state) or 'rows' (into `out` when given). Returns its outputs (N,
    n_out), or None when the model has no such kernel or the float kernel raised (sqrt of a
    negative pivot, a zero pivot: callers report it by the reference)."""
    b = bind(slot(model), model, spec)
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
    as the Spec's Result says and scattered into place (Kernel.scatter). Returns (N,) + the
    Result's shape; c_order: the rows kernel writes a C-ordered array (else it returns the
    transpose of a state-last one). None: no kernel, the vectorised reference is faster, or
    the outputs failed the check (the reference then reports it), or a build this thread defers."""
    N = len(arrays[0])
    if later(model, spec):
        return None
    if mode is None and native_first:
        nk = native(model, spec)
        if nk is not None:
            r = nk(*arrays)
            if r is None and not all(a.flags.c_contiguous for a in arrays):
                r = nk(*[np.ascontiguousarray(a) for a in arrays])
            if r is not None:
                return r
    mode = check_mode(mode) or route(model, spec.limits, N)
    b = bind(slot(model), model, spec) if mode else False
    if not b:
        return None
    k = b.kernel
    shape = (N,) + b.result.shape
    if k.scatter is not None:
        vals = _scattered(b, spec, arrays, mode)
        return None if vals is None else vals.reshape(shape)
    vals = _evaluate(b, spec, arrays, mode, np.empty((N, k.n_out)) if c_order and mode == 'rows' else None)
    if vals is None:
        return None
    _, m, rtol = b.result
    if rtol is not None:
        if not accepts(vals, m, rtol):
            return None
        vals = vals[:, :m]
    return vals.reshape(shape)


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
