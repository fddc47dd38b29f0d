"""A kernel's description (`Spec`), its run-time parameters and the one acceptance rule.

A kernel is described by a `Spec` (its traced form lives in codegen/traced/): how to build it
from the model's Frames, which parameter lists follow the per-state arguments, which entry of
THRESHOLDS says when it runs and how its outputs are accepted (`Result`). Per structure it is
one kernel.Kernel (cache.entry); with the parameter lists of one model version it is a `Bound`.
"""
from typing import NamedTuple

import numpy as np

from .cache import derived, entry, frames, python_sized, slot
from ..validation import finite


class Result(NamedTuple):
    """What a kernel's outputs are for one state: the first `size` values are the result, of
    `shape`; rtol None, or the outputs after them are pivots then their scales, as many each,
    accepted above rtol times the scale (`accepts`)."""
    shape: tuple
    size: int
    rtol: float = None


class Spec:
    """A generated kernel: `name` (its cache key: specs of one name share the compiled code),
    `build(frames)` -> its kernel.Trace or None, `params` (the parameter lists that follow
    its per-state arguments, the trace's Params lists in order: PARAMETERS keys, or
    functions (model) -> tuple), `limits` (its THRESHOLDS entry), `supports` (an extra
    condition on the model, or None), `rows_arrays` (parameters of the rows form as 0-d
    arrays, see as_rows), `checked` (the outputs are checked: the rows form runs without
    floating-point warnings), `pooled` (the batch runner keeps its register blocks between
    calls: batch.run_rows), `rows_chunk` (None, or the THRESHOLDS entry bounding the states of
    one rows call), `result` (model) -> (shape of one state's result, rtol), read as a
    `Result` by `result_of` (None: all outputs as a vector), and `looped` (None, or (frames) ->
    native.Rendered or None: the looped native form of the same steps, codegen/looped.py, which
    replaces the straight-line C form from THRESHOLDS[limits].looped_from)."""
    __slots__ = ('name', 'build', 'params', 'limits', 'supports', 'rows_arrays', 'checked', 'pooled', 'result',
                 'rows_chunk', 'looped')

    def __init__(self, name, build, params, limits, supports=None, rows_arrays=False, checked=False,
                 pooled=False, result=None, rows_chunk=None, looped=None):
        self.name, self.build, self.params, self.limits = name, build, tuple(params), limits
        self.supports, self.rows_arrays, self.checked, self.pooled = supports, rows_arrays, checked, pooled
        self.result, self.rows_chunk, self.looped = result, rows_chunk, looped

    def variant(self, params):
        """The same kernel with other parameter lists (e.g. gravity switched off)."""
        return Spec(self.name, self.build, params, self.limits, self.supports, self.rows_arrays, self.checked,
                    self.pooled, self.result, self.rows_chunk, self.looped)


def result_of(model, spec, n_out):
    """spec's Result for this model (n_out: the kernel's number of outputs, the result when
    spec.result is None)."""
    shape, rtol = spec.result(model) if spec.result else ((n_out,), None)
    return Result(tuple(shape), int(np.prod(shape)), rtol)


def accepts(vals, m, rtol):
    """Outputs of a kernel with pivots (Result) for one state (a sequence) or a batch (N, k): a
    finite result (the first m) and every pivot above rtol times its scale (the outputs after
    the result: pivots, then as many scales). The one acceptance rule of the Python kernels
    (native_call.c applies it to the C kernels' outputs)."""
    if isinstance(vals, np.ndarray):
        p = (vals.shape[1] - m) // 2
        return bool(np.all(np.isfinite(vals[:, :m])) and np.all(vals[:, m:m + p] > rtol * vals[:, m + p:]))
    p = (len(vals) - m) // 2
    return finite(sum(vals[:m])) and all(d > rtol * c for d, c in zip(vals[m:m + p], vals[m + p:], strict=True))


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
              'no_gravity': lambda model, fr: (0.0, 0.0, 0.0),
              'armature': lambda model, fr: tuple(model.armature.tolist())}


def parameter(model, kind):
    """One parameter list of the kernels, in the primed frames (codegen.frames), cached until
    the model's version changes: 'inertia' (10 per body), 'subtree' (gravity kernel, 4 per
    body), 'gravity' (-g), 'no_gravity' (zeros), 'offsets' (body offsets of locked and
    offset joints) or 'armature' (one per joint, Model.armature)."""
    return derived(model, kind, lambda: PARAMETERS[kind](model, frames(model)))


def parameters(model, spec):
    """spec's parameter lists for this model's version (PARAMETERS keys or functions of the model)."""
    return tuple(parameter(model, p) if isinstance(p, str) else p(model) for p in spec.params)


def as_rows(values):
    """Parameter lists as 0-d arrays, for the rows kernels: a ufunc takes a 0-d array operand
    ~0.25 us faster than a Python float (no scalar conversion per call)."""
    return tuple(tuple(np.array(v) for v in vs) for vs in values)


# ---------------------------------------------------------------------------- kernels
def kernel(model, spec):
    """spec's Kernel for this model with its Python forms built, or None: too large for
    THRESHOLDS (compile_max), screws other than unit revolute / prismatic axes, or
    spec.supports(model) false."""
    k = entry(model, spec)
    return k if k is not None and python_sized(model, spec) and k.python() else None


class Bound:
    """spec's Kernel with the parameter lists of one model version: `kernel`, `function` (its
    float function), `params` and `rows_params` (those of the rows form), `result` (Result)."""
    __slots__ = ('kernel', 'function', 'params', 'rows_params', 'result')

    def __init__(self, k, params, rows_params, result):
        self.kernel, self.function, self.params, self.rows_params = k, k.function, params, rows_params
        self.result = result


def bind(s, model, spec):
    """The Bound of spec for the model's version (s: its cache.Slot), or False (no kernel)."""
    b = s.values.get(spec)
    if b is None:
        k = kernel(model, spec)
        b = False
        if k:
            P = parameters(model, spec)
            if len(P) != k.roles.count('param'):
                raise ValueError(f'kernel {spec.name}: {len(P)} parameter lists for {k.roles.count("param")}')
            b = Bound(k, P, as_rows(P) if spec.rows_arrays else P, result_of(model, spec, k.n_out))
        s.values[spec] = b
    return b


def params(model, spec, rows=False):
    """The parameter lists of spec's kernel (for its rows form when rows), cached until the
    model's version changes; None when the model has no such kernel."""
    b = bind(slot(model), model, spec)
    return (b.rows_params if rows else b.params) if b else None
