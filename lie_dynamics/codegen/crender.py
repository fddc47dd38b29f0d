"""The C renderer: a traced graph (tracer.py) as C source, for the native backend (native.py).

The same graph the Python renderers (render.py) turn into source, written as C: every live
node one `const double` (the compiler allocates registers), sums in the order and with the
constants of the Python rendering (render.form_text), so that, compiled without
-ffast-math and with -ffp-contract=off, results equal the Python float kernel's to the bit
(sin, cos and sqrt are the C library's in both). The entry point is

    void NAME(const double *const *in, const double *const *par, double *out)

in[i] the i-th per-state argument list, par[j] the j-th parameter list, out the outputs:
n_out values, or, with `index`, the values scattered into `size` slots (zeros elsewhere).

A graph of more than `part` nodes (THRESHOLDS['native_part']) is cut, in node order, into
parts of at most `part` nodes, each its own function: gcc's register allocation grows faster
than a straight-line body (one 7,500-node function: 1.3-1.8 s of compiler time; cut into
parts of 500 nodes: 0.6 s, on both cores). A value a later part reads passes through a slot
of one local array (a slot is reused once its last reader has run); storing a double and
loading it back changes no bit, so the parts compute what one function computes. The last
part writes the outputs, after every read of the inputs. emit_c joins the parts as separate
translation units (UNIT between them), for compiling them in parallel.
"""
from .render import form_text
from .thresholds import THRESHOLDS
from .tracer import Sym

_INCLUDES = ['#include <math.h>', '#include <string.h>']
_PART_ATTR = '__attribute__((noinline, visibility("hidden")))'


# Between translation units in one C text (emit_c; the whole text is valid C as well):
# native._build compiles the units in parallel and links them once.
UNIT = '/* lie_dynamics: translation unit */\n'


def literal(c):
    """A C double literal of c (repr keeps every bit)."""
    s = repr(float(c))
    return s if any(ch in s for ch in '.en') else s + '.0'


def node_text(op, data, ref, call=None):
    """C text of one graph node's value: a product, a reciprocal, a linear form, or a function of
    one argument (`call`: the C function's name, default the op's). ref(arg, need) names an
    argument. The one text of a node for the one-state and the across-states renderings."""
    if op == 'mul':
        return f'{ref(data[0], 3)}*{ref(data[1], 3)}'
    if op == 'inv':
        return f'1.0/{ref(data, 3)}'
    if op == 'lin':
        return form_text(data[0], data[1], ref, literal)[0]
    return f'{call or op}({ref(data, 0)})'


def output_text(o, ref):
    """C text of one kernel output: a linear form of graph values (a Sym) or a constant."""
    return form_text(tuple(o.terms.items()), o.const, ref, literal)[0] if isinstance(o, Sym) else literal(o)


def emit_c(g, fname, arg_lists, roles, outputs, index=None, size=None, part='auto'):
    """C source of kernel `fname` (module docstring): its translation units, one per part,
    joined by UNIT. arg_lists: [(list name, [input names])], roles: per list 'state' or
    'param' (per-state lists first, in order, then parameters); part: nodes per function
    ('auto': THRESHOLDS['native_part'], None: one function)."""
    part = THRESHOLDS['native_part'] if part == 'auto' else part
    return UNIT.join(emit_c_units(g, fname, arg_lists, roles, outputs, index, size, part))


def emit_c_units(g, fname, arg_lists, roles, outputs, index=None, size=None, part=None):
    """emit_c as a list of translation units (C texts), one per part, the entry point `fname`
    in the last; part: nodes per function (None: one function)."""
    where = {}
    ks = {'state': 0, 'param': 0}
    for (_, syms), role in zip(arg_lists, roles, strict=True):
        arr = 'in' if role == 'state' else 'par'
        k = ks[role]
        ks[role] += 1
        for pos, nm in enumerate(syms):
            where[nm] = f'{arr}{k}[{pos}]'
    _, live = g.live(outputs)
    order = [i for i in sorted(live) if g.nodes[i][0] != 'in']
    n_parts = max(1, -(-len(order) // part)) if part else 1
    per = -(-len(order) // n_parts) if order else 1
    home = {i: k // per for k, i in enumerate(order)}     # node -> its part
    for i in live:
        if g.nodes[i][0] == 'in':
            home[i] = -1                                  # inputs: read where needed
    groups = [[] for _ in range(n_parts)]
    for i in order:
        groups[home[i]].append(i)
    slots, n_slots = {}, 0
    if n_parts > 1:   # slots for values read by a later part, reused after their last reader
        last = {}
        for i in order:
            for a in g.deps(i):
                last[a] = max(last.get(a, -1), home[i])
        for o in outputs:
            if isinstance(o, Sym):
                for a in o.terms:
                    last[a] = n_parts - 1
        free, ending = [], {}
        for p in range(n_parts):
            free.extend(slots[i] for i in ending.pop(p - 1, ()))
            for i in groups[p]:
                if last.get(i, p) > p:
                    slots[i] = free.pop() if free else n_slots
                    n_slots = max(n_slots, slots[i] + 1)
                    ending.setdefault(last[i], []).append(i)

    def ref_in(p):
        def ref(a, need):
            if home[a] == -1:
                return where[g.nodes[a][1]]
            return f't{a}' if home[a] == p or n_parts == 1 else f's[{slots[a]}]'
        return ref

    def body_of(p):
        ref = ref_in(p)
        lines = []
        for i in groups[p]:
            op, data = g.nodes[i]
            lines.append(f'  const double t{i} = {node_text(op, data, ref)};')
            if i in slots:
                lines.append(f'  s[{slots[i]}] = t{i};')
        if p < n_parts - 1:
            return lines
        if index is not None:
            lines.append(f'  memset(out, 0, {int(size)} * sizeof(double));')
        for k, o in enumerate(outputs):   # after every read of the inputs, as `out` may alias them
            lines.append(f'  out[{k if index is None else int(index[k])}] = {output_text(o, ref)};')
        return lines

    def pointers():
        return [f'  const double *{arr}{k} = {arr}[{k}]; (void){arr}{k};'
                for role, arr in (('state', 'in'), ('param', 'par')) for k in range(ks[role])]
    head = f'void {fname}(const double *const *in, const double *const *par, double *out)'
    if n_parts == 1:
        return ['\n'.join(_INCLUDES + [head, '{'] + pointers() + body_of(0) + ['}']) + '\n']
    proto = [f'{_PART_ATTR} void {fname}_p{p}(const double *const *in, const double *const *par, '
             f'double *restrict s, double *out)' for p in range(n_parts)]
    texts = [_INCLUDES + [proto[p], '{'] + pointers() + body_of(p) + ['}'] for p in range(n_parts)]
    texts[-1] += [f'{pr};' for pr in proto] + [head, '{', f'  double s[{max(n_slots, 1)}];']
    texts[-1] += [f'  {fname}_p{p}(in, par, s, out);' for p in range(n_parts)] + ['}']
    return ['\n'.join(t) + '\n' for t in texts]


def emit_step(g, fname, inputs, outputs):
    """C text of one looped step (looped.py): `static inline void fname(const double *a0, ...,
    double *o0, ...)`, inputs: [input names] per pointer argument, outputs: [Syms or floats] per
    output pointer. Every output is computed before the first is stored, so an output pointer
    may alias an input (a register block updated in place)."""
    where = {nm: f'a{k}[{pos}]' for k, names in enumerate(inputs) for pos, nm in enumerate(names)}
    _, live = g.live([o for outs in outputs for o in outs])
    order = [i for i in sorted(live) if g.nodes[i][0] != 'in']

    def ref(a, need):
        return where[g.nodes[a][1]] if g.nodes[a][0] == 'in' else f't{a}'
    args = [f'const double *a{k}' for k in range(len(inputs))] + [f'double *o{k}' for k in range(len(outputs))]
    lines = [f'static inline void {fname}({", ".join(args)})', '{']
    lines += [f'  (void)a{k};' for k in range(len(inputs))]
    lines += [f'  const double t{i} = {node_text(*g.nodes[i], ref)};' for i in order]
    stores = []
    for k, outs in enumerate(outputs):
        for pos, o in enumerate(outs):
            lines.append(f'  const double r{k}_{pos} = {output_text(o, ref)};')
            stores.append(f'  o{k}[{pos}] = r{k}_{pos};')
    return '\n'.join(lines + stores + ['}']) + '\n'
