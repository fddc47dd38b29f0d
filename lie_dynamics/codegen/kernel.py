"""The one kernel type: a traced algorithm of one model structure and its three renderings.

A `Trace` is what a traced form (codegen/traced/) returns: the graph, the argument lists
with their roles (per-state inputs first, then parameters, marked render.Params) and the
outputs. A `Kernel` carries everything the renderers and the runtime use of one kernel:

  * the trace (built on first need, dropped once rendered; traced again if asked for later),
  * the float function (render.emit, one state) and its source,
  * the rows function (render.emit_rows, a batch; compiled on first use),
  * the native entry (crender.emit_c compiled by native.py, from the disk cache when there:
    then the algorithm is never traced in this process),
  * the argument roles and widths, the number of outputs and, for a kernel whose outputs
    are the non-zero entries of a larger result, where they go (`scatter`, `packer`).
"""
import enum
import struct
import threading

import numpy as np

from . import clanes, crender, native as _native
from .render import Params, compile_function, emit, emit_rows, rows_env
from .thresholds import THRESHOLDS

_BUILDS = [0]   # traces rendered in this process (runtime.cache_info)


def builds():
    """Kernels traced and rendered (Python or C) since the process started."""
    return _BUILDS[0]


class NativeState(enum.Enum):
    """A Kernel's native library before it is a native.Library: not asked for yet, or unavailable
    (backend off, no compiler, too many nodes)."""
    UNTRIED = 'untried'
    UNAVAILABLE = 'unavailable'


class Trace:
    """A traced kernel (the intermediate form): `graph` (tracer.Graph), `name` (of the rendered
    function), `arguments` ([(list name, [input names])] in call order: per-state lists first,
    then parameter lists, render.Params), `outputs` (Syms or floats) and `scatter`: None, or
    (flat indices, size) when the outputs are the non-zero entries of a result of `size`
    values (zeros elsewhere)."""
    __slots__ = ('graph', 'name', 'arguments', 'outputs', 'scatter')

    def __init__(self, graph, name, arguments, outputs, scatter=None):
        self.graph, self.name, self.arguments, self.outputs = graph, name, list(arguments), list(outputs)
        self.scatter = None if scatter is None else (np.asarray(scatter[0], dtype=np.intp), int(scatter[1]))
        roles = self.roles
        if 'param' in roles and 'state' in roles[roles.index('param'):]:
            raise ValueError(f'kernel {name}: per-state argument lists must come before the parameters')

    @property
    def roles(self):
        """'state' or 'param' per argument list."""
        return tuple('param' if isinstance(a, Params) else 'state' for a in self.arguments)


def _packer(index, size):
    """A struct writing the outputs at `index` of a float64 buffer of `size` values, the rest as
    pad bytes (packed as NUL bytes, i.e. 0.0): ~3x faster than np.array of the outputs."""
    keep = np.zeros(size, bool)
    keep[index] = True
    fmt, i = [], 0
    while i < size:
        j = i
        while j < size and keep[j] == keep[i]:
            j += 1
        fmt.append(f'{j - i}d' if keep[i] else f'{8 * (j - i)}x')
        i = j
    return struct.Struct('=' + ''.join(fmt))   # native byte order, no alignment


class Kernel:
    """One generated kernel of one model structure (shared by the models of that structure).

    `name` (its cache key), `frames` (codegen.frames.Frames, or None), `structure` (the
    model fingerprint, None: no native entry); from the trace: `roles` ('state' / 'param'
    per argument list), `widths` (values per argument list), `n_state` (per-state lists),
    `n_out`, `scatter` and `packer` (Trace.scatter; packer.pack_into(buffer, offset,
    *outputs) writes one state's full result); the renderings: `function` and `source`
    (floats), `rows()` (numpy rows), `native()` (C; `native_state`: NativeState.UNTRIED, UNAVAILABLE
    or the native.Library). `python()` builds the Python forms, False when the structure has no
    such kernel (the traced form returned None).
    """
    __slots__ = ('name', 'frames', 'structure', '_build', '_trace', '_lock', '_native_lock', 'supported',
                 'function', 'source', 'rows_source', 'nreg', '_rows', 'n_out', 'roles', 'widths', 'n_state',
                 'scatter', 'packer', 'native_state', 'looped', '__weakref__')

    def __init__(self, build, name, frames=None, structure=None, looped=None):
        """build() -> Trace or None; traced on first need. looped: None, or () -> native.Rendered
        or None, the looped C form (codegen/looped.py) that native() compiles instead of rendering
        the trace (which it then never needs)."""
        self.name, self.frames, self.structure, self._build = name, frames, structure, build
        self.looped = looped
        # two locks: a C compile (seconds) never holds up a thread that needs the Python forms
        self._trace, self._lock, self._native_lock, self.supported = None, threading.Lock(), threading.Lock(), None
        self.function = self.source = self.rows_source = self.nreg = self._rows = None
        self.n_out = self.roles = self.widths = self.n_state = self.scatter = self.packer = None
        self.native_state = NativeState.UNTRIED

    @classmethod
    def of(cls, trace):
        """The Kernel of a Trace, its Python forms built."""
        k = cls(lambda: trace, trace.name)
        k.python()
        return k

    def trace(self):
        """The Trace (traced now when it was dropped), or None (no such kernel)."""
        t = self._trace
        if t is None and self.supported is not False:
            t = self._build()
            self.supported = t is not None
            if t is not None:
                self.n_out = len(t.scatter[0]) if t.scatter else len(t.outputs)
                self.roles = t.roles
                self.widths = tuple(len(a[1]) for a in t.arguments)
                self.n_state = self.roles.count('state')
                if t.scatter is not None:
                    self.scatter, self.packer = t.scatter, _packer(*t.scatter)
                self._trace = t
        return t

    def built(self, native, python=True):
        """Whether calling it builds nothing. native: its C library is wanted (then loaded, or
        known to be unavailable); python: its Python forms, where no C library serves."""
        if native:
            if self.native_state is NativeState.UNTRIED:
                return False
            if self.native_state is not NativeState.UNAVAILABLE:
                return True
        return not python or self.function is not None or self.supported is False

    def python(self):
        """Build the float function and the rows source (once); False when there is no kernel."""
        if self.function is not None:
            return True
        with self._lock:
            if self.function is None:
                t = self.trace()
                if t is None:
                    return False
                src = emit(t.graph, t.name, t.arguments, t.outputs)
                fn = compile_function(src, t.name)
                self.rows_source, self.nreg = emit_rows(t.graph, t.name + '_rows', t.arguments, t.outputs)
                self.source, self.function = src, fn
                _BUILDS[0] += 1
                if self.native_state is not NativeState.UNTRIED or self.structure is None or not _native.wanted():
                    self._trace = None   # no C rendering will need it
        return True

    def rows(self):
        """The compiled numpy-rows function, compiled on first use: callers that only ever run
        one state (a controller) do not pay for it (about a sixth of a build)."""
        fn = self._rows
        if fn is None:
            self.python()
            ns = dict(rows_env())
            name = self.function.__name__ + '_rows'
            exec(compile(self.rows_source, f'<lie_dynamics generated {name}>', 'exec'), ns)
            fn = self._rows = ns[name]
        return fn

    def native(self):
        """The compiled C kernel (native.Library) of this structure, or None (backend off or
        unavailable, no structure, no kernel, or more nodes than THRESHOLDS native_nodes)."""
        lib = self.native_state
        if lib is NativeState.UNTRIED:
            if self.structure is None:
                return None
            with self._native_lock:
                lib = self.native_state
                if lib is NativeState.UNTRIED:
                    name, render, flags = ((self.name + ':looped', self._render_looped, _native.LOOPED_FLAGS)
                                           if self.looped is not None
                                           else (self.name, self._render_c, _native.KERNEL_FLAGS))
                    lib = _native.library(self.structure, name, render, flags) or NativeState.UNAVAILABLE
                    self.native_state = lib
                    self._trace = None   # rendered (or loaded without a trace): the Python forms retrace
        return None if lib is NativeState.UNAVAILABLE else lib

    def _render_looped(self):
        r = self.looped()
        _BUILDS[0] += r is not None
        return r

    def _render_c(self):
        """The native.Rendered C form for native.library, or None."""
        t = self.trace()
        if t is None or len(t.graph.live(t.outputs)[1]) > THRESHOLDS['native_nodes']:
            return None
        index, size = t.scatter if t.scatter else (None, None)
        src = crender.emit_c(t.graph, 'lie_kernel', t.arguments, t.roles, t.outputs, index, size)
        if self.name in clanes.FAMILIES and len(t.graph.live(t.outputs)[1]) <= THRESHOLDS['native_lanes_nodes']:
            src += _native.UNIT + clanes.emit_lanes(t.graph, 'lie_kernel_lanes', t.arguments, t.roles, t.outputs,
                                                    index, size)
        _BUILDS[0] += 1
        ns = self.n_state
        return _native.Rendered(src, tuple(self.widths[:ns]), tuple(self.widths[ns:]), size or len(t.outputs))
