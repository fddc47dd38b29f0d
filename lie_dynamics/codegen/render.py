"""Renderers: a traced graph (tracer.py) as Python source, compiled once per model structure.

The same traced algorithm is rendered twice:
  * `emit`: a function on Python floats, for one state (no numpy call at all; a numpy call
    costs about a microsecond whatever its size, so one state through stacked 6x6 matrices
    is mostly call overhead), and
  * `emit_rows`: a function on numpy rows with one entry per state, for a batch (state-last
    rows; each operation is one ufunc whose fixed cost the whole chunk shares).
kernel.Kernel compiles the float form and keeps the rows form's source (compiled on first use).
The third rendering, C for the native backend, is crender.py. Argument lists are per-state
values unless marked as parameters (Params).
"""
import math

import numpy as np

from .tracer import Sym

def form_text(items, const, ref, literal=repr):
    """Text of sum c_k * atom_k + const; ref(atom, need) gives an atom's text, literal a
    constant's (the C renderer shares this: the same order of operations, the same results)."""
    items = sorted(items, key=lambda t: t[1] < 0)   # a positive term first when there is one
    out = []
    for k, (a, c) in enumerate(items):
        mag = abs(c)
        body = ref(a, 2) if mag == 1.0 else f'{literal(mag)}*{ref(a, 3)}'
        if c < 0:
            out.append(('-' if k == 0 else ' - ') + body)
        else:
            out.append(('' if k == 0 else ' + ') + body)
    if const != 0.0:
        out.append(f' - {literal(-const)}' if const < 0 else f' + {literal(const)}')
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
    Three passes on the graph: which nodes become lines (the rest is inlined), registers for
    those lines (_registers), then the text.
    """
    deps = g.deps
    roots, live = g.live(outputs)
    uses = {}
    for i in live:
        for a in deps(i):
            uses[a] = uses.get(a, 0) + 1
    for a in roots:
        uses[a] = uses.get(a, 0) + 2
    order = sorted(live)
    inlined, size, seq = set(), {}, {}

    def leaves(a):   # the non-inlined nodes node a's text names, in text order
        return seq[a] if a in inlined else [a]

    def form_leaves(items, const):
        rec = []
        form_text(items, const, lambda a, need: rec.extend(leaves(a)) or 'x')
        return rec

    lines = []       # nodes that become a line
    for i in order:
        op, data = g.nodes[i]
        if op == 'in':
            continue
        if op == 'mul':
            seq[i] = leaves(data[0]) + leaves(data[1])
        elif op == 'lin':
            seq[i] = form_leaves(data[0], data[1])
        else:
            seq[i] = leaves(data)
        n_ops = 1 + sum(size.get(a, 0) for a in deps(i) if a in inlined)
        if uses.get(i, 0) == 1 and n_ops < inline_limit:
            inlined.add(i)
            size[i] = n_ops
        else:
            lines.append(i)
    ret_leaves = [a for o in outputs if isinstance(o, Sym) for a in form_leaves(tuple(o.terms.items()), o.const)]
    regs = _registers(g, lines, seq, ret_leaves)

    names, text = dict(regs), {}

    def ref(a, need):
        if a in text:
            s, p = text[a]
            return f'({s})' if p < need else s
        return names[a]

    body = []
    for i in order:
        op, data = g.nodes[i]
        if op == 'in':
            names[i] = data
            continue
        if op == 'mul':
            s, p = f'{ref(data[0], 2)}*{ref(data[1], 3)}', 2
        elif op == 'inv':
            s, p = f'1.0/{ref(data, 3)}', 2
        elif op == 'lin':
            s, p = form_text(data[0], data[1], ref)
        else:
            s, p = f'{op}({ref(data, 0)})', _PREC_ATOM
        if i in inlined:
            text[i] = (s, p)
        else:
            body.append((names[i], s))

    def out(o):
        if not isinstance(o, Sym):
            return repr(float(o))
        return form_text(tuple(o.terms.items()), o.const, ref)[0]

    ret = f'({", ".join(out(o) for o in outputs)}{"," if len(outputs) == 1 else ""})'
    params = [n for n, _ in arg_lists] + ['sin=sin_', 'cos=cos_', 'sqrt=sqrt_']
    hot = _hot_locals(lines, seq, ret_leaves, names, [nm for _, syms in arg_lists for nm in syms],
                      _MAX_FAST - len(params))
    head = [f'def {fname}({", ".join(params + [f"{h}=0.0" for h in hot])}):']
    for lname, syms in arg_lists:
        if syms:
            head.append(f'    {", ".join(syms)}{"," if len(syms) == 1 else ""} = {lname}')
    return '\n'.join(head + [f'    {t} = {x}' for t, x in body] + [f'    return {ret}']) + '\n'


# CPython addresses the first 256 local variables with a one-byte argument; every access to a
# later one costs an extra EXTENDED_ARG instruction (about 10-15% of a large kernel's time).
_MAX_FAST = 256


def _registers(g, lines, seq, ret_leaves):
    """{node: register name} for the nodes of `lines` (in order), a name reused once its value
    is dead (linear scan over the graph's uses: seq[i], the nodes line i reads, in text order;
    ret_leaves, those the return reads). Fewer distinct locals keep most of them within the
    first 256 (see _MAX_FAST)."""
    temps = set(lines)
    last = {}
    for k, i in enumerate(lines):
        for x in seq[i]:
            if x in temps:
                last[x] = k
    for x in ret_leaves:
        if x in temps:
            last[x] = len(lines)
    regs, free, nreg = {}, [], 0
    for k, i in enumerate(lines):
        for x in dict.fromkeys(seq[i]):
            if x in temps and last[x] == k:
                free.append(regs[x])
        if free:
            regs[i] = free.pop()
        else:
            regs[i], nreg = f'r{nreg}', nreg + 1
    return regs


def _hot_locals(lines, seq, ret_leaves, names, inputs, k):
    """The k most used locals (registers and unpacked inputs), to be declared first.

    Locals are numbered in order of first appearance after the parameters; declaring the
    busiest ones as parameters with defaults (filled in from a tuple at no cost) gives them
    the one-byte numbers.
    """
    count = dict.fromkeys(inputs, 0)
    for i in lines:
        count[names[i]] = count.get(names[i], 0) + 1
        for x in seq[i]:
            count[names[x]] += 1
    for x in ret_leaves:
        count[names[x]] += 1
    if len(count) <= k:
        return []
    return sorted(count, key=lambda x: -count[x])[:k]


def compile_function(src, fname):
    ns = dict(sin_=math.sin, cos_=math.cos, sqrt_=math.sqrt, tanh=math.tanh)   # the defaults of sin, cos, sqrt
    exec(compile(src, f'<lie_dynamics generated {fname}>', 'exec'), ns)
    return ns[fname]


class Params(tuple):
    """An argument list of parameters, (name, symbol names): the same for every state of a
    batch (Python floats in the rows rendering, hoisted out of the per-state work). Any other
    argument list, a plain (name, symbol names) pair, holds per-state values."""
    __slots__ = ()

    def __new__(cls, name, syms):
        return super().__new__(cls, (name, list(syms)))


def emit_rows(g, fname, arg_lists, outputs):
    """(source, register count) of `def fname(*arg_lists, B)` for batches: per-state inputs
    are numpy rows (one entry per state), parameters Python floats.

    Every operation on rows is one ufunc writing into a register row of B (nreg + 1 rows, the
    last a scratch row) with out=, so a chunk allocates nothing but its outputs. Nodes that
    depend on parameters only are computed once per call as Python floats. A register is
    reused once its value is dead, never as the target of an operation that reads it.
    """
    roots, live = g.live(outputs)
    scalar_in = {nm for lst in arg_lists if isinstance(lst, Params) for nm in lst[1]}
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
        elif op in ('sin', 'cos', 'sqrt', 'tanh'):
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
                 sin=np.sin, cos=np.cos, sqrt=np.sqrt, sin_=math.sin, cos_=math.cos, sqrt_=math.sqrt,
                 tanh=np.tanh, tanh_=math.tanh)


def rows_env():
    """The names the rows rendering's source refers to (numpy ufuncs, math for parameters)."""
    return _ROWS_ENV
