"""The tracer: an algorithm written on scalars, run on symbols, becomes an expression graph.

Only +, -, *, unary minus, sin, cos, tanh, sqrt and 1/x are traced (a / b is a * (1/b); np.tanh of
a Sym is its tanh); no data-dependent branches.
Constants fold as they meet (zeros and ones of the home poses, joint axes and masks drop
out) and repeated subexpressions are shared; render.py turns the graph into source.
"""
import math

import numpy as np

# Constants this close to 0 or +-1 are snapped (URDF rpy of pi/2 give cos = 6e-17 instead of 0),
# so that whole products fold away. The change is below the rounding of the URDF text itself.
SNAP = 1e-15


def snap(a):
    a = np.array(a, dtype=float, copy=True)
    for t in (0.0, 1.0, -1.0):
        a[np.abs(a - t) < SNAP] = t
    return a


class Sym:
    """A traced scalar: a linear form sum_k c_k atom_k + const over atoms of graph `g`.

    Atoms are inputs, products of two atoms, sin/cos of an atom, or a materialised linear
    form. Keeping sums as forms lets signs and constant factors ride along for free and
    lets exactly cancelling terms (cross products of parallel vectors, ...) vanish.
    """
    __slots__ = ('g', 'terms', 'const')

    def __init__(self, g, terms, const=0.0):
        self.g, self.terms, self.const = g, terms, const

    def __add__(self, o):
        return self.g.add(self, o, 1.0)

    def __radd__(self, o):
        return self.g.add(o, self, 1.0)

    def __sub__(self, o):
        return self.g.add(self, o, -1.0)

    def __rsub__(self, o):
        return self.g.add(o, self, -1.0)

    def __mul__(self, o):
        return self.g.mul(self, o)

    def __rmul__(self, o):
        return self.g.mul(o, self)

    def __neg__(self):
        return self.g.scale(self, -1.0)

    def __pos__(self):
        return self

    def __truediv__(self, o):
        # traced as a * (1/b): the tracer has 1/x, not a division (1 ulp from numpy's a / b)
        return self.g.mul(self, self.g.inv(o))

    def tanh(self):
        # np.tanh of a Sym calls this: numpy code with tanh (laws.friction_torque) traces as is
        return self.g.tanh(self)


def _const(x):
    return not isinstance(x, Sym)


class Graph:
    """Records traced operations with constant folding and common-subexpression sharing."""

    # Sums longer than this are materialised as a node. 1 (every sum of two terms is a node)
    # measured fastest: longer forms re-add the same partial sums in different products.
    MAX_TERMS = 1

    def __init__(self):
        self.nodes = []      # (op, data): 'in' name | 'mul' (a, b) | 'sin'/'cos' a | 'lin' (terms, const)
        self.memo = {}

    def _atom(self, op, data):
        key = (op, data)
        i = self.memo.get(key)
        if i is None:
            i = len(self.nodes)
            self.nodes.append((op, data))
            self.memo[key] = i
        return i

    def input(self, name):
        return Sym(self, {self._atom('in', name): 1.0})

    def _make(self, terms, const):
        terms = {a: c for a, c in terms.items() if c != 0.0}
        if not terms:
            return const
        if len(terms) > self.MAX_TERMS:
            c, a = self._materialise(terms, const)
            return Sym(self, {a: c})
        return Sym(self, terms, const)

    def _materialise(self, terms, const):
        """(c, atom) with c * atom = the form; the sign is factored out exactly."""
        items = tuple(sorted(terms.items()))
        s = -1.0 if items[0][1] < 0 else 1.0
        if s < 0:
            items = tuple((a, -c) for a, c in items)
            const = -const
        return s, self._atom('lin', (items, const))

    def atom_of(self, x):
        """(c, atom) with c * atom = x for a Sym."""
        if x.const == 0.0 and len(x.terms) == 1:
            (a, c), = x.terms.items()
            return c, a
        return self._materialise(x.terms, x.const)

    def add(self, a, b, sb):
        if _const(a) and _const(b):
            return float(a) + sb * float(b)
        if _const(a):
            terms = {k: sb * c for k, c in b.terms.items()}
            return self._make(terms, float(a) + sb * b.const)
        terms = dict(a.terms)
        const = a.const
        if _const(b):
            return self._make(terms, const + sb * float(b))
        for k, c in b.terms.items():
            terms[k] = terms.get(k, 0.0) + sb * c
        return self._make(terms, const + sb * b.const)

    def scale(self, a, k):
        if _const(a):
            return k * float(a)
        if k == 0.0:
            return 0.0
        return self._make({t: k * c for t, c in a.terms.items()}, k * a.const)

    def mul(self, a, b):
        if _const(a):
            return self.scale(b, float(a))
        if _const(b):
            return self.scale(a, float(b))
        ca, x = self.atom_of(a)
        cb, y = self.atom_of(b)
        m = self._atom('mul', (x, y) if x <= y else (y, x))
        return Sym(self, {m: ca * cb})

    def bake(self, x):
        """x with its constant factor inside its atom, so that products with it need no extra
        multiply (worth it for a value scaled once and multiplied many times)."""
        if _const(x) or (x.const == 0.0 and len(x.terms) == 1 and abs(next(iter(x.terms.values()))) == 1.0):
            return x
        s, a = self._materialise(x.terms, x.const)
        return Sym(self, {a: s})

    def fn(self, name, a):
        if _const(a):
            return getattr(math, name)(a)
        if a.const == 0.0 and len(a.terms) == 1 and next(iter(a.terms.values())) == 1.0:
            x = next(iter(a.terms))
        else:
            x = self._atom('lin', (tuple(sorted(a.terms.items())), a.const))
        return Sym(self, {self._atom(name, x): 1.0})

    def sqrt(self, a):
        return self.fn('sqrt', a)

    def inv(self, a):
        """1 / a."""
        if _const(a):
            return 1.0 / float(a)
        c, x = self.atom_of(a)
        return Sym(self, {self._atom('inv', x): 1.0 / c})

    def sin(self, a):
        return self.fn('sin', a)

    def deps(self, i):
        """The atoms node i is computed from."""
        op, data = self.nodes[i]
        if op == 'in':
            return []
        if op == 'mul':
            return list(data)
        if op == 'lin':
            return [a for a, _ in data[0]]
        return [data]

    def live(self, outputs):
        """(atoms the outputs read directly, every atom they depend on)."""
        roots = [a for o in outputs if isinstance(o, Sym) for a in o.terms]
        live, stack = set(), list(roots)
        while stack:
            i = stack.pop()
            if i not in live:
                live.add(i)
                stack.extend(self.deps(i))
        return roots, live

    def cos(self, a):
        return self.fn('cos', a)

    def tanh(self, a):
        return self.fn('tanh', a)

