"""The C renderer: a traced graph (tracer.py) as one C function, for the native backend (native.py).

The same graph the Python renderers (render.py) turn into source, written as C: every live
node one `const double` (the compiler allocates registers), sums in the order and with the
constants of the Python rendering (render.form_text), so that, compiled without
-ffast-math and with -ffp-contract=off, results equal the Python float kernel's to the bit
(sin, cos and sqrt are the C library's in both). The function is

    void NAME(const double *const *in, const double *const *par, double *out)

in[i] the i-th per-state argument list, par[j] the j-th parameter list, out the outputs:
n_out values, or, with `index`, the values scattered into `size` slots (zeros elsewhere).
"""
from .render import form_text
from .tracer import Sym


def _literal(c):
    s = repr(float(c))
    return s if any(ch in s for ch in '.en') else s + '.0'


def emit_c(g, fname, arg_lists, roles, outputs, index=None, size=None):
    """C source of kernel `fname` (module docstring). arg_lists: [(list name, [input names])],
    roles: per list 'state' or 'param' (per-state lists first, in order, then parameters)."""
    where = {}
    ks = {'state': 0, 'param': 0}
    for (_, syms), role in zip(arg_lists, roles, strict=True):
        arr = 'in' if role == 'state' else 'par'
        k = ks[role]
        ks[role] += 1
        for pos, nm in enumerate(syms):
            where[nm] = f'{arr}{k}[{pos}]'
    roots, live = g.live(outputs)
    names = {}

    def ref(a, need):
        return names[a]

    body = []
    for i in sorted(live):
        op, data = g.nodes[i]
        if op == 'in':
            names[i] = where[data]
            continue
        if op == 'mul':
            s = f'{names[data[0]]}*{names[data[1]]}'
        elif op == 'inv':
            s = f'1.0/{names[data]}'
        elif op == 'lin':
            s = form_text(data[0], data[1], ref, _literal)[0]
        else:
            s = f'{op}({names[data]})'
        names[i] = f't{i}'
        body.append(f'  const double t{i} = {s};')

    def out(o):
        if not isinstance(o, Sym):
            return _literal(o)
        return form_text(tuple(o.terms.items()), o.const, ref, _literal)[0]

    head = [f'void {fname}(const double *const *in, const double *const *par, double *out)', '{']
    for role, arr in (('state', 'in'), ('param', 'par')):
        for k in range(ks[role]):
            head.append(f'  const double *{arr}{k} = {arr}[{k}]; (void){arr}{k};')
    if index is None:
        tail = [f'  out[{k}] = {out(o)};' for k, o in enumerate(outputs)]
    else:
        tail = [f'  for (int k = 0; k < {size}; ++k) out[k] = 0.0;']
        tail += [f'  out[{int(j)}] = {out(o)};' for j, o in zip(index, outputs, strict=True)]
    return '\n'.join(head + body + tail + ['}']) + '\n'
