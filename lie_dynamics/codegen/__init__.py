"""Straight-line code by tracing: an algorithm written on scalars becomes a compiled function.

A numpy call costs about a microsecond whatever its size, so one robot state pushed through
stacks of 6x6 matrices is mostly call overhead. Here an algorithm is written once on plain
scalars (Python floats or the symbols below) and traced with the model's constants folded
in: zeros and ones of the home poses, joint axes and masks drop out, repeated
subexpressions are shared, and what remains is emitted as Python source and compiled once
per model. The same compiled function runs

  * on Python floats, for one state (no numpy call at all), and
  * on numpy arrays with one entry per state, for a batch (state-last rows; each operation
    is one ufunc whose cost the whole batch shares).

Only +, -, *, unary minus, sin and cos are traced; no data-dependent branches.
"""
import hashlib
import math
import re
import weakref

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


def _render_form(items, const, ref):
    """Text of sum c_k * atom_k + const; ref(atom, need) gives an atom's text."""
    items = sorted(items, key=lambda t: t[1] < 0)   # a positive term first when there is one
    out = []
    for k, (a, c) in enumerate(items):
        mag = abs(c)
        body = ref(a, 2) if mag == 1.0 else f'{mag!r}*{ref(a, 2)}'
        if c < 0:
            out.append(('-' if k == 0 else ' - ') + body)
        else:
            out.append(('' if k == 0 else ' + ') + body)
    if const != 0.0:
        out.append(f' - {-const!r}' if const < 0 else f' + {const!r}')
    s = ''.join(out)
    single = len(items) == 1 and const == 0.0
    if single and items[0][1] == 1.0:
        return s, _PREC_ATOM
    return s, (2 if single and items[0][1] > 0 else 1)


_PREC_ATOM = 4


def emit(g, fname, arg_lists, outputs, inline_limit=24):
    """Python source of `def fname(*arg_lists, sin, cos, sqrt)` returning the tuple `outputs`
    (sin, cos, sqrt default to math's; callers may pass others).

    arg_lists: [(list name, [input symbol names])]; outputs: Syms or floats. Dead nodes are
    dropped; intermediate atoms used once are inlined into their consumer (bounded length).
    """
    deps = g.deps
    roots, live = g.live(outputs)
    uses = {}
    for i in live:
        for a in deps(i):
            uses[a] = uses.get(a, 0) + 1
    for a in roots:
        uses[a] = uses.get(a, 0) + 2
    names, text, size, lines = {}, {}, {}, []

    def ref(a, need):
        if a in text:
            s, p = text[a]
            return f'({s})' if p < need else s
        return names[a]

    for i in sorted(live):
        op, data = g.nodes[i]
        if op == 'in':
            names[i] = data
            continue
        if op == 'mul':
            s, p = f'{ref(data[0], 2)}*{ref(data[1], 2)}', 2
        elif op == 'inv':
            s, p = f'1.0/{ref(data, 3)}', 2
        elif op == 'lin':
            s, p = _render_form(data[0], data[1], ref)
        else:
            s, p = f'{op}({ref(data, 0)})', _PREC_ATOM
        n_ops = 1 + sum(size.get(a, 0) for a in deps(i) if a in text)
        if uses.get(i, 0) == 1 and n_ops < inline_limit:
            text[i], size[i] = (s, p), n_ops
        else:
            names[i] = f't{len(lines)}'
            lines.append((names[i], s))

    def out(o):
        if not isinstance(o, Sym):
            return repr(float(o))
        return _render_form(tuple(o.terms.items()), o.const, ref)[0]

    ret = f'({", ".join(out(o) for o in outputs)}{"," if len(outputs) == 1 else ""})'
    lines, ret = _registers(lines, ret)
    params = [n for n, _ in arg_lists] + ['sin=sin_', 'cos=cos_', 'sqrt=sqrt_']
    hot = _hot_locals(lines, ret, [nm for _, syms in arg_lists for nm in syms], _MAX_FAST - len(params))
    head = [f'def {fname}({", ".join(params + [f"{h}=0.0" for h in hot])}):']
    for lname, syms in arg_lists:
        if syms:
            head.append(f'    {", ".join(syms)}{"," if len(syms) == 1 else ""} = {lname}')
    return '\n'.join(head + [f'    {t} = {x}' for t, x in lines] + [f'    return {ret}']) + '\n'


# Identifiers of the generated text (not the exponent of a float literal such as 1e-05).
_IDENT = re.compile(r'(?<![\w.])[A-Za-z_]\w*')
# CPython addresses the first 256 local variables with a one-byte argument; every access to a
# later one costs an extra EXTENDED_ARG instruction (about 10-15% of a large kernel's time).
_MAX_FAST = 256


def _registers(lines, ret):
    """Rename temporaries so that a name is reused once its value is dead (linear scan).

    Fewer distinct locals keep most of them within the first 256 (see _MAX_FAST).
    lines: [(temp, expression)] in order; ret: the return expression.
    """
    temps = {t for t, _ in lines}
    toks = [[x for x in _IDENT.findall(e) if x in temps] for _, e in lines]
    last = {}
    for i, ts in enumerate(toks):
        for x in ts:
            last[x] = i
    for x in _IDENT.findall(ret):
        if x in temps:
            last[x] = len(lines)
    regs, free, nreg = {}, [], 0
    for i, ((t, _), ts) in enumerate(zip(lines, toks)):
        for x in dict.fromkeys(ts):
            if last[x] == i:
                free.append(regs[x])
        if free:
            regs[t] = free.pop()
        else:
            regs[t], nreg = f'r{nreg}', nreg + 1

    def ren(e):
        return _IDENT.sub(lambda m: regs.get(m.group(0), m.group(0)), e)
    return [(regs[t], ren(e)) for t, e in lines], ren(ret)


def _hot_locals(lines, ret, inputs, k):
    """The k most used locals (registers and unpacked inputs), to be declared first.

    Locals are numbered in order of first appearance after the parameters; declaring the
    busiest ones as parameters with defaults (filled in from a tuple at no cost) gives them
    the one-byte numbers.
    """
    count = dict.fromkeys(inputs, 0)
    for t, e in lines:
        count[t] = count.get(t, 0) + 1
        for x in _IDENT.findall(e):
            if x in count:
                count[x] += 1
    for x in _IDENT.findall(ret):
        if x in count:
            count[x] += 1
    if len(count) <= k:
        return []
    return sorted(count, key=lambda x: -count[x])[:k]


def compile_function(src, fname):
    ns = dict(sin_=math.sin, cos_=math.cos, sqrt_=math.sqrt)   # the defaults of sin, cos, sqrt
    exec(compile(src, f'<lie_dynamics generated {fname}>', 'exec'), ns)
    return ns[fname]


# Names of the argument lists that hold parameters (the same for every state of a batch);
# every other list holds per-state values, rows in the numpy rendering.
SCALAR_LISTS = ('P', 'A0', 'E0')


def emit_rows(g, fname, arg_lists, outputs):
    """(source, register count) of `def fname(*arg_lists, B)` for batches: per-state inputs
    are numpy rows (one entry per state), parameters Python floats.

    Every operation on rows is one ufunc writing into a register row of B (nreg + 1 rows, the
    last a scratch row) with out=, so a chunk allocates nothing but its outputs. Nodes that
    depend on parameters only are computed once per call as Python floats. A register is
    reused once its value is dead, never as the target of an operation that reads it.
    """
    roots, live = g.live(outputs)
    scalar_in = {nm for lname, syms in arg_lists if lname in SCALAR_LISTS for nm in syms}
    is_row = {}
    for i in sorted(live):
        op, data = g.nodes[i]
        is_row[i] = data not in scalar_in if op == 'in' else any(is_row[a] for a in g.deps(i))
    last = {}
    order = [i for i in sorted(live) if g.nodes[i][0] != 'in']
    for k, i in enumerate(order):
        for a in g.deps(i):
            last[a] = k
    for a in roots:
        last[a] = len(order)
    names, free, nreg, lines = {}, [], 0, []

    def name(a):
        return names[a] if a in names else g.nodes[a][1]

    def scalar_part(terms, const):
        parts = [repr(const)] if const != 0.0 else []
        parts += [f'{c!r}*{name(a)}' for a, c in terms]
        return ' + '.join(parts) if parts else None

    for k, i in enumerate(order):
        op, data = g.nodes[i]
        if not is_row[i]:   # parameters only: a Python float
            names[i] = f'u{i}'
            if op == 'mul':
                e = f'{name(data[0])}*{name(data[1])}'
            elif op == 'lin':
                e = scalar_part(data[0], data[1]) or '0.0'
            elif op == 'inv':
                e = f'1.0/{name(data)}'
            else:
                e = f'{op}_({name(data)})'
            lines.append(f'{names[i]} = {e}')
            continue
        if free:
            R = free.pop()
        else:
            R, nreg = f'r{nreg}', nreg + 1
        if op == 'mul':
            lines.append(f'multiply({name(data[0])}, {name(data[1])}, out={R})')
        elif op == 'inv':
            lines.append(f'divide(1.0, {name(data)}, out={R})')
        elif op in ('sin', 'cos', 'sqrt'):
            lines.append(f'{op}({name(data)}, out={R})')
        else:
            terms, const = data
            rterms = [(a, c) for a, c in terms if is_row[a]]
            S = scalar_part([(a, c) for a, c in terms if not is_row[a]], const)
            rterms.sort(key=lambda t: t[1] != 1.0)          # a +1 term first when there is one
            (a1, c1), rest = rterms[0], rterms[1:]
            if c1 == 1.0 and rest and abs(rest[0][1]) == 1.0:
                (a2, c2), rest = rest[0], rest[1:]
                lines.append(f'{"add" if c2 > 0 else "subtract"}({name(a1)}, {name(a2)}, out={R})')
            elif c1 == 1.0 and rest:   # a1 + c2 a2 + ...: the scaled term first, then a1
                (a2, c2), rest = rest[0], rest[1:]
                lines.append(f'multiply({name(a2)}, {c2!r}, out={R})')
                lines.append(f'{R} += {name(a1)}')
            elif c1 == 1.0 and S is not None:
                lines.append(f'add({name(a1)}, {S}, out={R})')
                S = None
            elif c1 == -1.0 and S is not None:
                lines.append(f'subtract({S}, {name(a1)}, out={R})')
                S = None
            else:
                lines.append(f'multiply({name(a1)}, {c1!r}, out={R})')
            for a, c in rest:
                if abs(c) == 1.0:
                    lines.append(f'{R} {"+" if c > 0 else "-"}= {name(a)}')
                else:
                    lines.append(f'multiply({name(a)}, {abs(c)!r}, out=TMP)')
                    lines.append(f'{R} {"+" if c > 0 else "-"}= TMP')
            if S is not None:
                lines.append(f'{R} += {S}')
        names[i] = R
        for a in dict.fromkeys(g.deps(i)):   # after the target: it must differ from its operands
            if a in names and is_row[a] and last.get(a) == k:
                free.append(names[a])

    def out(o):
        if not isinstance(o, Sym):
            return repr(float(o))
        if o.const == 0.0 and len(o.terms) == 1 and next(iter(o.terms.values())) == 1.0:
            return name(next(iter(o.terms)))
        return '(' + ' + '.join([f'{c!r}*{name(a)}' for a, c in o.terms.items()]
                                + ([repr(o.const)] if o.const != 0.0 else [])) + ')'

    head = [f'def {fname}({", ".join(n for n, _ in arg_lists)}, B):']
    for lname, syms in arg_lists:
        if syms:
            head.append(f'    {", ".join(syms)}{"," if len(syms) == 1 else ""} = {lname}')
    head.append(f'    {", ".join([f"r{k}" for k in range(nreg)] + ["TMP"])}, = B')
    ret = f'    return ({", ".join(out(o) for o in outputs)}{"," if len(outputs) == 1 else ""})'
    return '\n'.join(head + [f'    {x}' for x in lines] + [ret]) + '\n', nreg


_ROWS_ENV = dict(multiply=np.multiply, add=np.add, subtract=np.subtract, divide=np.divide,
                 sin=np.sin, cos=np.cos, sqrt=np.sqrt, sin_=math.sin, cos_=math.cos, sqrt_=math.sqrt)


def kernel(g, fname, arg_lists, outputs):
    """(function, float source): the traced outputs compiled for Python floats (one state),
    with the numpy-rows rendering as attributes rows_source / nreg (see rows_function)."""
    src = emit(g, fname, arg_lists, outputs)
    fn = compile_function(src, fname)
    fn.rows_source, fn.nreg = emit_rows(g, fname + '_rows', arg_lists, outputs)
    fn.rows = None
    return fn, src


def rows_function(fn):
    """The compiled numpy-rows rendering of a kernel, compiled on first use: callers that
    only ever run one state (a controller) do not pay for it (about a sixth of a build)."""
    if fn.rows is None:
        ns = dict(_ROWS_ENV)
        name = fn.__name__ + '_rows'
        exec(compile(fn.rows_source, f'<lie_dynamics generated {name}>', 'exec'), ns)
        fn.rows = ns[name]
    return fn.rows


# ---------------------------------------------------------------------------- small linear algebra
# 3-vectors are tuples, 3x3 matrices tuples of rows; entries are floats or Syms.
def mat_vec(R, v):
    return tuple(R[r][0] * v[0] + R[r][1] * v[1] + R[r][2] * v[2] for r in range(3))


def mat_t_vec(R, v):
    return tuple(R[0][c] * v[0] + R[1][c] * v[1] + R[2][c] * v[2] for c in range(3))


def mat_mat(A, B):
    return tuple(tuple(A[r][0] * B[0][c] + A[r][1] * B[1][c] + A[r][2] * B[2][c] for c in range(3))
                 for r in range(3))


def cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def dot(a, b):
    s = 0.0
    for x, y in zip(a, b):
        s = s + x * y
    return s


def vadd(a, b):
    return tuple(x + y for x, y in zip(a, b))


def vsub(a, b):
    return tuple(x - y for x, y in zip(a, b))


def vscale(k, a):
    return tuple(k * x for x in a)


def sym_rot(R, I):
    """R I R^T for symmetric I given as (xx, xy, xz, yy, yz, zz); same layout out."""
    xx, xy, xz, yy, yz, zz = I
    Im = ((xx, xy, xz), (xy, yy, yz), (xz, yz, zz))
    RI = mat_mat(R, Im)
    def e(r, c):
        return RI[r][0] * R[c][0] + RI[r][1] * R[c][1] + RI[r][2] * R[c][2]
    return (e(0, 0), e(0, 1), e(0, 2), e(1, 1), e(1, 2), e(2, 2))


def sym_vec(I, v):
    xx, xy, xz, yy, yz, zz = I
    return (xx * v[0] + xy * v[1] + xz * v[2], xy * v[0] + yy * v[1] + yz * v[2],
            xz * v[0] + yz * v[1] + zz * v[2])


# ---------------------------------------------------------------------------- running kernels
def is_fast_single(x, n):
    """A plain finite (n,) float state as a list, else None (callers then validate in full)."""
    if type(x) is np.ndarray and x.shape == (n,) and x.dtype == np.float64:
        lst = x.tolist()
    elif type(x) in (list, tuple) and len(x) == n:
        try:
            lst = [float(v) for v in x]
        except (TypeError, ValueError):
            return None
    else:
        return None
    s = sum(lst)
    return lst if s - s == 0.0 else None


def run_rows(fn, args, n_out, chunk=None):
    """Run a kernel (`kernel`) on a batch: args in the kernel's argument order, (N, k) arrays for
    the per-state lists and lists of floats for the parameters -> (N, n_out).

    States go in chunks, transposed to state-last rows, through rows_function(fn) with one preallocated
    register block. The chunk is large enough that each ufunc's fixed cost is shared, small
    enough that the rows stay in cache (at most ~8 MB of registers).
    """
    rows_fn = rows_function(fn)
    idx = [i for i, a in enumerate(args) if isinstance(a, np.ndarray)]
    N = args[idx[0]].shape[0]
    rows = {i: np.ascontiguousarray(args[i].T) for i in idx}
    size = chunk or int(min(4096, max(256, (8 << 20) // (8 * (fn.nreg + 1)))))
    B = np.empty((fn.nreg + 1, min(size, N)))
    out = np.empty((n_out, N))
    for s in range(0, N, size):
        sl = slice(s, min(N, s + size))
        call = [list(rows[i][:, sl]) if i in rows else a for i, a in enumerate(args)]
        with np.errstate(all='ignore'):   # callers check the results (e.g. Cholesky pivots)
            res = rows_fn(*call, list(B[:, :sl.stop - s]))
        for k, v in enumerate(res):
            out[k, sl] = v
    return out.T


# ---------------------------------------------------------------------------- model structure
def axis_frame(a):
    """Proper rotation Q with Q e_z = a (a signed permutation when a is a coordinate axis)."""
    a = np.asarray(a, dtype=float)
    nz = np.flatnonzero(np.abs(a) > 0)
    if len(nz) == 1:
        u = np.zeros(3)
        u[(int(nz[0]) + 1) % 3] = 1.0
    else:
        e = np.zeros(3)
        e[int(np.argmin(np.abs(a)))] = 1.0
        u = np.cross(e, a)
        u /= np.linalg.norm(u)
    return np.column_stack([u, np.cross(a, u), a])


class Frames:
    """Per-model constants for kernels: body frames turned so that every joint axis is z.

    Body frame b' = body frame b rotated by Q_b (Q_b e_z = joint axis). Then
    f_{p',b'}(x) = M'_b Rz(x) (revolute) or M'_b Trans(x e_z) (prismatic), with the
    constant M'_b = (R'_b, t'_b) = (Q_p^T R_b Q_b, Q_p^T p_b). Inertias are runtime
    parameters moved to the primed frames (`inertia_params`), so payload, gravity and
    locked-joint changes never recompile.
    """

    def __init__(self, model):
        self.nb, self.n = model.nb, model.n
        self.parent = [int(p) for p in model.parent]
        w, v = model.S[:, :3], model.S[:, 3:]
        nw, nv = np.linalg.norm(w, axis=1), np.linalg.norm(v, axis=1)
        self.revolute = [bool(abs(a - 1) < 1e-12 and b == 0) for a, b in zip(nw, nv)]
        prismatic = [bool(a == 0 and abs(b - 1) < 1e-12) for a, b in zip(nw, nv)]
        self.supported = all(r or p for r, p in zip(self.revolute, prismatic))
        if not self.supported:
            return
        self.Q = np.array([axis_frame(w[b] if self.revolute[b] else v[b]) for b in range(self.nb)])
        self.R, self.t = [], []
        for b in range(self.nb):
            p = self.parent[b]
            Qp = self.Q[p] if p >= 0 else np.eye(3)
            R = snap(Qp.T @ model.M[b, :3, :3] @ self.Q[b])
            self.R.append(tuple(tuple(float(x) for x in row) for row in R))
            self.t.append(tuple(float(x) for x in snap(Qp.T @ model.M[b, :3, 3])))
        self.E = model.E.copy()
        self.offset = [bool(np.any(model.L[b] != 0) or model.c0[b] != 0) for b in range(self.nb)]
        self.children = [[] for _ in range(self.nb)]
        for b, p in enumerate(self.parent):
            if p >= 0:
                self.children[p].append(b)

    def inertia_table(self, J):
        """(nb, 10) array: per body (m, h, I_xx, I_xy, I_xz, I_yy, I_yz, I_zz) in the primed frame."""
        Qt = np.swapaxes(self.Q, 1, 2)
        I = Qt @ J[:, :3, :3] @ self.Q
        h = np.einsum('bij,bj->bi', Qt, np.stack([J[:, 2, 4], J[:, 0, 5], J[:, 1, 3]], axis=1))
        return np.column_stack([J[:, 3, 3], h, I[:, 0, 0], I[:, 0, 1], I[:, 0, 2], I[:, 1, 1],
                                I[:, 1, 2], I[:, 2, 2]])

    def inertia_params(self, J):
        """inertia_table as one flat list (the P argument of the traced kernels)."""
        return self.inertia_table(J).reshape(-1).tolist()

    def wrench_params(self, fext):
        """(..., nb, 6) body-frame wrenches (n, f) -> the same in the primed frames (Q^T n, Q^T f)."""
        out = np.empty_like(fext)
        out[..., :3] = np.einsum('bji,...bj->...bi', self.Q, fext[..., :3])
        out[..., 3:] = np.einsum('bji,...bj->...bi', self.Q, fext[..., 3:])
        return out

    def offsets(self, e0):
        return [float(e0[b]) for b in range(self.nb) if self.offset[b]]

    # ---- tracing helpers
    def trace_coordinates(self, g, rates=0):
        """Symbols for q (and qd, qdd) and the body coordinates; returns dict of lists."""
        n, nb = self.n, self.nb
        out = {'args': []}
        q = [g.input(f'q{j}') for j in range(n)]
        out['args'].append(('Q', [f'q{j}' for j in range(n)]))
        e = {b: g.input(f'e{b}') for b in range(nb) if self.offset[b]}
        x = []
        for b in range(nb):
            s = e.get(b, 0.0)
            for j in range(n):
                s = s + float(self.E[b, j]) * q[j]
            x.append(s)
        out['x'] = x
        for k, (nm, lst) in enumerate((('QD', 'qv'), ('QDD', 'qa'))[:rates]):
            syms = [g.input(f'{lst}{j}') for j in range(n)]
            out['args'].append((nm, [f'{lst}{j}' for j in range(n)]))
            xs = []
            for b in range(nb):
                s = 0.0
                for j in range(n):
                    s = s + float(self.E[b, j]) * syms[j]
                xs.append(s)
            out['xd' if k == 0 else 'xdd'] = xs
        out['offset_args'] = ('E0', [f'e{b}' for b in range(nb) if self.offset[b]])
        return out

    def trace_params(self, g):
        names = [f'p{b}_{k}' for b in range(self.nb) for k in range(10)]
        syms = [g.input(nm) for nm in names]
        per = [syms[10 * b:10 * b + 10] for b in range(self.nb)]
        return ('P', names), [(p[0], tuple(p[1:4]), tuple(p[4:10])) for p in per]

    def joint_transform(self, g, b, x):
        """(R, t) of f_{p',b'}(x) as traced 3x3 / 3-vector."""
        R0, t0 = self.R[b], self.t[b]
        if self.revolute[b]:
            c, s = g.cos(x), g.sin(x)
            Rz = ((c, -s, 0.0), (s, c, 0.0), (0.0, 0.0, 1.0))
            return mat_mat(R0, Rz), t0
        return R0, vadd(t0, vscale(x, (R0[0][2], R0[1][2], R0[2][2])))

    def project(self, Mx):
        """E^T Mx E for a traced nb x nb nested list."""
        E, n, nb = self.E, self.n, self.nb
        out = [[0.0] * n for _ in range(n)]
        for a in range(n):
            for c in range(n):
                s = 0.0
                for i in range(nb):
                    if E[i, a] == 0:
                        continue
                    for j in range(nb):
                        if E[j, c] != 0:
                            s = s + float(E[i, a] * E[j, c]) * Mx[i][j]
                out[a][c] = s
        return out


_MODEL_CACHE = weakref.WeakKeyDictionary()
_COMPILED = {}


def model_cache(model):
    """A per-model dict for derived constants, dropped with the model (never pickled with it)."""
    c = _MODEL_CACHE.get(model)
    if c is None:
        c = _MODEL_CACHE[model] = {}
    return c


def frames(model):
    """Cached Frames of a model (structure never changes after construction)."""
    c = model_cache(model)
    f = c.get('frames')
    if f is None:
        f = c['frames'] = Frames(model)
    return f


def fingerprint(model):
    """Hash of everything a kernel's source depends on (copies of a model share kernels)."""
    c = model_cache(model)
    fp = c.get('fingerprint')
    if fp is None:
        h = hashlib.sha1()
        for a in (model.M, model.S, model.parent, model.E, model.L != 0, model.c0 != 0):
            h.update(np.ascontiguousarray(a).tobytes())
            h.update(str(np.shape(a)).encode())
        fp = c['fingerprint'] = h.hexdigest()
    return fp


def compiled(model, name, build):
    """The kernel `name` of this model's structure: build(frames) once per structure.

    Returns build's result, or False when the model is unsupported or build returns None.
    """
    mc = model_cache(model)
    k = mc.get(('kernel', name))
    if k is not None:
        return k
    key = (fingerprint(model), name)
    k = _COMPILED.get(key)
    if k is None:
        fr = frames(model)
        k = build(fr) if fr.supported else None
        k = _COMPILED[key] = (fr,) + tuple(k) if k is not None else False
    mc[('kernel', name)] = k
    return k


def model_params(model, fr, gravity=False):
    """Runtime parameter lists (P, E0[, A0]) of the kernels, cached until J, e0 or gravity change.

    A0 = -g, the linear part of the base acceleration (0, -g).
    """
    mc = model_cache(model)
    c = mc.get('params')
    if c is None or c[0] is not model.J or c[1] is not model.e0 or c[2] is not model.base_acceleration:
        c = mc['params'] = (model.J, model.e0, model.base_acceleration, fr.inertia_params(model.J), fr.offsets(model.e0),
                            model.base_acceleration[3:].tolist())
    return (c[3], c[4], c[5]) if gravity else (c[3], c[4])


def inertia_to_parent(ic, R, t):
    """Inertia (m, h, I) of a body in frame b' expressed about frame p', with f_{p',b'} = (R, t).

    h' = R h + m t,  I' = R I R^T + m(|t|^2 1 - t t^T) + 2 (t . R h) 1 - t (R h)^T - (R h) t^T.
    """
    m, h, I = ic
    Rh = mat_vec(R, h)
    hp = vadd(Rh, vscale(m, t))
    Ir = sym_rot(R, I)
    tt = dot(t, t)
    th = dot(t, Rh)
    d = m * tt + 2.0 * th
    pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    Ip = []
    for k, (r, c) in enumerate(pairs):
        v = Ir[k] - m * (t[r] * t[c]) - (t[r] * Rh[c] + Rh[r] * t[c])
        if r == c:
            v = v + d
        Ip.append(v)
    return m, hp, tuple(Ip)


def wrench_to_parent(F, R, t):
    """A wrench (n, f) in frame b' expressed in frame p': (R n + t x R f, R f)."""
    n_, f_ = F
    Rf = mat_vec(R, f_)
    return vadd(mat_vec(R, n_), cross(t, Rf)), Rf


def inertia_times(ic, V):
    """J V for J = [[I, [h]], [-[h], m 1]] and V = (w, v): (I w + h x v, m v - h x w)."""
    m, h, I = ic
    w, v = V
    return vadd(sym_vec(I, w), cross(h, v)), vsub(vscale(m, v), cross(h, w))


def bracket(X, Y):
    """[X, Y] = ad_X Y for twists X = (w1, v1), Y = (w2, v2): (w1 x w2, w1 x v2 + v1 x w2)."""
    (w1, v1), (w2, v2) = X, Y
    return cross(w1, w2), vadd(cross(w1, v2), cross(v1, w2))


def ad_t(X, F):
    """ad_X^T F for a twist X = (w, v) and a wrench F = (n, f): (-(w x n) - v x f, -(w x f))."""
    (w, v), (n_, f_) = X, F
    return vscale(-1.0, vadd(cross(w, n_), cross(v, f_))), vscale(-1.0, cross(w, f_))


def inertia_rate(ic, V):
    """d/dt of a root-frame inertia (m, h, I) moving with twist V = (w, v): (0, hdot, Idot).

    hdot = w x h + m v,  Idot = [w] I - I [w] + 2 (h . v) 1 - v h^T - h v^T.
    (Equals -(ad_V^T J + J ad_V) in 6x6 form, with 10 numbers instead of 21.)
    """
    m, h, I = ic
    w, v = V
    hd = vadd(cross(w, h), vscale(m, v))
    xx, xy, xz, yy, yz, zz = I
    Im = ((xx, xy, xz), (xy, yy, yz), (xz, yz, zz))
    W = ((0.0, -w[2], w[1]), (w[2], 0.0, -w[0]), (-w[1], w[0], 0.0))
    WI = mat_mat(W, Im)  # [w] I ; I [w] = -( [w] I )^T since I sym, [w] skew
    hv = 2.0 * dot(h, v)
    out = []
    for r, c in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)):
        e = WI[r][c] + WI[c][r] - (v[r] * h[c] + h[r] * v[c])
        if r == c:
            e = e + hv
        out.append(e)
    return 0.0, hd, tuple(out)


def inertia_add(a, b):
    return a[0] + b[0], vadd(a[1], b[1]), vadd(a[2], b[2])


def twist_add(a, b):
    return vadd(a[0], b[0]), vadd(a[1], b[1])


def twist_scale(k, a):
    return vscale(k, a[0]), vscale(k, a[1])


def dot6(a, b):
    return dot(a[0], b[0]) + dot(a[1], b[1])


def twist_to_child(V, R, t):
    """Ad_{f^-1} V for f = (R, t) (frame b' in p'): a twist in p' expressed in b'."""
    w, v = V
    return mat_t_vec(R, w), mat_t_vec(R, vsub(v, cross(t, w)))


def trace_rnea(fr, g, x, xd, xdd, params, a0, X=None):
    """Body-torques of the RNEA (paper eqs 16-21) in the primed frames, traced.

    x, xd, xdd: body coordinates and rates; params: per body (m, h, I); a0: base linear
    acceleration -g (3 values); X: optional precomputed joint transforms.
    """
    nb = fr.nb
    zero3 = (0.0, 0.0, 0.0)
    X = X or [fr.joint_transform(g, b, x[b]) for b in range(nb)]
    V, A, F = [None] * nb, [None] * nb, [None] * nb
    for b in range(nb):
        p = fr.parent[b]
        Vp, Ap = (V[p], A[p]) if p >= 0 else ((zero3, zero3), (zero3, tuple(a0)))
        R, t = X[b]
        S = ((0.0, 0.0, 1.0), zero3) if fr.revolute[b] else (zero3, (0.0, 0.0, 1.0))
        Sxd = twist_scale(xd[b], S)
        V[b] = twist_add(twist_to_child(Vp, R, t), Sxd)                            # eq 18
        A[b] = twist_add(twist_add(twist_to_child(Ap, R, t), twist_scale(xdd[b], S)),
                         bracket(V[b], Sxd))                                         # eq 19
        H = inertia_times(params[b], V[b])
        F[b] = twist_add(inertia_times(params[b], A[b]), twist_scale(-1.0, ad_t(V[b], H)))   # eq 20
    tau = [None] * nb
    for b in reversed(range(nb)):
        tau[b] = F[b][0][2] if fr.revolute[b] else F[b][1][2]                       # eq 21
        p = fr.parent[b]
        if p >= 0:
            F[p] = twist_add(F[p], wrench_to_parent(F[b], *X[b]))
    return tau
