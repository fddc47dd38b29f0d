"""The one validation of the library's arguments: shapes and finiteness, with ValueErrors naming
the argument.

Every algorithm entry point validates its per-state arguments once, through `states` (as
`Model.validate`), before it routes them to a kernel or its reference; what runs after that
takes the validated arrays and never checks them again. `float_lists` is the same rule for the
fast path of one state (codegen.dispatch), which declines (None) instead of raising, so that
the full path names the problem. `vector` checks a fixed-size vector (gravity, a payload's CoM,
a Jacobian's point). Finiteness of many values is one exact test of their sum (`finite`).
"""
from typing import NamedTuple

import numpy as np

_ND = np.ndarray
_F64 = np.dtype(float)


def finite(s):
    """Whether the float s, a sum of the values to check, is finite, and so is each of them:
    inf - inf and nan are not 0. One exact test for any number of values (an overflow to inf
    of finite values only means a check one by one)."""
    return s - s == 0.0


class States(NamedTuple):
    """Validated per-state arguments: `arrays`, (N, n) float arrays in the order given, and
    `single`, whether the call is one state (its first argument was (n,))."""
    arrays: list
    single: bool


_states = tuple.__new__   # _states(States, (arrays, single)): a States without the Python-level __new__


def batch(name, x, n, joints=None, N=None):
    """(n,) or (N, n) -> (N, n) float array; ValueError naming the argument (and the joints)."""
    a = np.asarray(x, dtype=float)
    if a.ndim == 1 and a.shape[0] == n:
        a = a[None]
    elif not (a.ndim == 2 and a.shape[1] == n):
        raise ValueError(f'{name} must have shape ({n},) or (N, {n}) for joints {joints}, got {np.shape(x)}')
    if N is not None and a.shape[0] != N:
        raise ValueError(f'{name} has {a.shape[0]} states, expected {N}')
    if not np.all(np.isfinite(a)):
        raise ValueError(f'{name} contains non-finite values')
    return a


def states(n, names, args, joints=None):
    """The validation of one call's per-state arguments (`names` name them in messages): a
    States. The common case is one check: arrays of one shape, (n,) or (N, n), with a finite
    sum (float64 ones are not copied). Anything else is checked argument by argument (`batch`:
    the first sets N), and the first bad one raises ValueError naming it."""
    try:
        arrs = [np.asarray(x, dtype=float) for x in args]
    except (ValueError, TypeError):
        arrs = None
    if arrs is not None:
        shape = arrs[0].shape
        if len(shape) in (1, 2) and shape[-1] == n and all(x.shape == shape for x in arrs):
            with np.errstate(over='ignore', invalid='ignore'):   # overflow only means: check exactly
                s = sum(float(x.sum()) for x in arrs)
            if finite(s):
                return _states(States, ([x[None] for x in arrs] if len(shape) == 1 else arrs, len(shape) == 1))
    out, N = [], None
    for name, x in zip(names, args, strict=True):
        a = batch(name, x, n, joints, N)
        N = a.shape[0]
        out.append(a)
    return _states(States, (out, np.ndim(args[0]) == 1))


def vector(name, x, n, what=''):
    """x as a finite (n,) float array; ValueError naming it (`what`: how to read it, in the message)."""
    a = np.array(x, dtype=float)   # a copy: the caller's array stays the caller's
    if a.shape != (n,):
        raise ValueError(f'{name} must have shape ({n},){what}, got {a.shape}')
    if not np.all(np.isfinite(a)):
        raise ValueError(f'{name} contains non-finite values')
    return a


def float_lists(widths, xs, count):
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
    return out if finite(s) else None


def float_list(x, n):
    """One (n,) float64 array or sequence of n numbers with a finite sum as a float list, or None."""
    lists = float_lists((n,), (x,), 1)
    return lists[0] if lists else None
