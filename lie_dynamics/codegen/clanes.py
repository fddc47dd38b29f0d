"""The C renderer across states: a traced graph as one C function on LANES states at once.

A traced kernel is straight-line code without branches, so the same graph runs on a vector of
LANES states with the compiler's vector types (GCC/Clang `vector_size`): each node that
depends on a state is one `lie_v` (LANES doubles), a node of parameters and constants alone
stays one `double`, computed once for the LANES states. The operations are those of the
one-state rendering (crender.py), in the same order with the same constants (render.form_text);
vector arithmetic is IEEE arithmetic lane by lane, sin, cos and sqrt are the C library's on
each lane (sincos where a node has both: the same functions, one argument reduction, as gcc
makes of the one-state kernel's sin and cos), and -ffp-contract=off forbids fused operations:
every lane equals the one-state kernel's result to the bit.

    int NAME(const double *const *in, const double *const *par, double *out)

in[i] the i-th per-state list of LANES consecutive states, row by row as a batch holds them
(value k of state l at in[i][l * width + k]), par[j] a parameter list as in crender, out the
LANES states' rows of outputs (n_out or `size` values each). It returns 1 when every output is
finite (their sum is, lane by lane), else 0. The rows are read into vectors and written from
them by the function itself, whose widths are constants: native_call.c hands it the batch's
rows in place (before: a transposition into a buffer and back, and the outputs' test state by
state, about a tenth of the batch's time). Every input is read before any output is written, so
`out` may be an input row for row.

The sin and cos of a per-state input (a revolute joint's angle) are not computed here: in[n]
and in[n + 1] (n per-state lists) hold the sines and the cosines of the inputs listed in the
table `lie_lanes_sincos` (count, then (list, position) pairs), LANES rows of `count` values.
native_call.c computes them with the C library's sincos for many states at once, grouped by
the branches the library takes (sincos_grouped): on angles over a joint's range those branches
are random, and in a batch's order mostly mispredicted (23 ns a call against 14 ns grouped,
bench.probes.batch_sincos). The values are the library's, whatever the order.

Instruction sets: on x86-64 under GCC or Clang the function is compiled twice
(`target_clones`): for AVX2 (4 doubles a vector) and for the baseline (SSE2, two halves), the
loader picks by the CPU it runs on; the cached library is then right on any x86-64 machine it
is copied to. Elsewhere the compiler's baseline vectors.
"""
from .crender import node_text, output_text

LANES = 4
# The kernels rendered across states too (kernel.Kernel's name): the form costs 2-4x the kernel's
# compile time at first use (two clones and the one-state form: inverse dynamics of the arm
# 0.5 -> 1.9 s, forward dynamics 0.9 -> 3.1 s on a loaded machine), paid where batches are the
# use: inverse dynamics (trajectories, identification) and gravity.
FAMILIES = ('inverse_dynamics', 'inverse_dynamics_wrench', 'gravity')

_HEAD = f'''#define _GNU_SOURCE
#include <math.h>
#include <string.h>
typedef double lie_v __attribute__((vector_size({8 * LANES}), aligned(8)));
#if defined(__x86_64__) && defined(__linux__) && defined(__has_attribute)
#if __has_attribute(target_clones)
#define LIE_CLONES __attribute__((target_clones("avx2", "default")))
#endif
#endif
#ifndef LIE_CLONES
#define LIE_CLONES
#endif
#define LIE_LANEWISE(NAME, F) static inline lie_v NAME(lie_v a) \\
  {{ lie_v r; for (int k = 0; k < {LANES}; ++k) r[k] = F(a[k]); return r; }}
LIE_LANEWISE(lie_vsin, sin)
LIE_LANEWISE(lie_vcos, cos)
#ifdef __GLIBC__
static inline void lie_vsincos(lie_v a, lie_v *s, lie_v *c)
  {{ for (int k = 0; k < {LANES}; ++k) sincos(a[k], &(*s)[k], &(*c)[k]); }}
#else
static inline void lie_vsincos(lie_v a, lie_v *s, lie_v *c) {{ *s = lie_vsin(a); *c = lie_vcos(a); }}
#endif
static inline lie_v lie_bc(double x) {{ lie_v r = {{{', '.join(['x'] * LANES)}}}; return r; }}
'''



def emit_lanes(g, fname, arg_lists, roles, outputs, index=None, size=None):
    """C source (one translation unit) of kernel `fname` on LANES states (module docstring);
    the arguments as crender.emit_c's."""
    where, lane, loads, place = {}, {}, {}, {}
    ks = {'state': 0, 'param': 0}
    for (_, syms), role in zip(arg_lists, roles, strict=True):
        arr = 'in' if role == 'state' else 'par'
        k = ks[role]
        ks[role] += 1
        for pos, nm in enumerate(syms):
            if role == 'state':   # value pos of the LANES consecutive rows (width len(syms)) of in{k}
                where[nm] = f'x{k}_{pos}'
                loads[nm] = _gather(f'{arr}{k}', len(syms), pos)
                place[nm] = (k, pos)
            else:
                where[nm] = f'{arr}{k}[{pos}]'
            lane[nm] = role == 'state'
    _, live = g.live(outputs)
    vec = {}
    for i in sorted(live):
        op, data = g.nodes[i]
        vec[i] = lane[data] if op == 'in' else any(vec[a] for a in g.deps(i))

    def ref(a, need):
        return where[g.nodes[a][1]] if g.nodes[a][0] == 'in' else f't{a}'

    # sin and cos of a per-state input come computed by the caller (module docstring): sincos[j] is
    # the (list, position) of the j-th such input
    given, sincos = {}, []
    for i in sorted(live):
        op, data = g.nodes[i]
        if op in ('sin', 'cos') and g.nodes[data][0] == 'in' and lane[g.nodes[data][1]]:
            if data not in given:
                given[data] = len(sincos)
                sincos.append(place[g.nodes[data][1]])
    n_sc = len(sincos)
    used = {g.nodes[a][1] for i in live if g.nodes[i][0] != 'in'
            and not (g.nodes[i][0] in ('sin', 'cos') and g.nodes[i][1] in given)
            for a in g.deps(i) if g.nodes[a][0] == 'in'}
    used |= {g.nodes[a][1] for o in outputs if hasattr(o, 'terms') for a in o.terms if g.nodes[a][0] == 'in'}
    n_state = ks['state']
    lines = [f'LIE_CLONES int {fname}(const double *const *in, const double *const *par, double *out)', '{']
    lines += [f'  const double *{arr}{k} = {arr}[{k}]; (void){arr}{k};'
              for role, arr in (('state', 'in'), ('param', 'par')) for k in range(ks[role])]
    lines.append(f'  const double *sin_in = in[{n_state}], *cos_in = in[{n_state + 1}]; (void)sin_in; (void)cos_in;')
    lines += [f'  const lie_v {where[nm]} = {txt};' for nm, txt in loads.items() if nm in used]
    both = {}   # argument -> its sin and cos nodes: one sincos call (glibc's sin and cos, one reduction)
    for i in sorted(live):
        op, data = g.nodes[i]
        if op in ('sin', 'cos') and vec[i] and data not in given:
            both.setdefault(data, {})[op] = i
    both = {a: d for a, d in both.items() if len(d) == 2}
    for i in sorted(live):
        op, data = g.nodes[i]
        if op == 'in':
            continue
        if op in ('sin', 'cos') and data in given:
            lines.append(f'  const lie_v t{i} = {_gather(op + "_in", n_sc, given[data])};')
            continue
        if op in ('sin', 'cos') and data in both:
            if i == min(both[data].values()):
                si, ci = both[data]['sin'], both[data]['cos']
                lines.append(f'  lie_v t{si}, t{ci}; lie_vsincos({ref(data, 0)}, &t{si}, &t{ci});')
            continue
        s = node_text(op, data, ref, f'lie_v{op}' if vec[i] else op)
        lines.append(f'  const {"lie_v" if vec[i] else "double"} t{i} = {s};')
    n_out = len(outputs) if index is None else int(size)
    if index is not None:
        lines.append(f'  memset(out, 0, {n_out * LANES} * sizeof(double));')
    total = []
    for k, o in enumerate(outputs):
        txt = output_text(o, ref)
        if not (hasattr(o, 'terms') and any(vec[a] for a in o.terms)):   # a scalar: broadcast to the lanes
            txt = f'lie_bc({txt})'
        slot = k if index is None else int(index[k])
        lines.append(f'  const lie_v o{k} = {txt};')
        lines += [f'  out[{l * n_out + slot}] = o{k}[{l}];' for l in range(LANES)]
        total.append(f'o{k}')
    # 1 when every output is finite: their sum is, in every lane (4 partial sums: independent additions)
    parts = [' + '.join(total[j::4]) for j in range(min(4, len(total)))] or ['lie_bc(0.0)']
    lines += [f'  const lie_v f{j} = {p};' for j, p in enumerate(parts)]
    lines.append('  const lie_v f = ' + ' + '.join(f'f{j}' for j in range(len(parts))) + ', z = f - f;')
    lines.append('  return ' + ' && '.join(f'z[{l}] == 0.0' for l in range(LANES)) + ';')
    fns = sorted({g.nodes[i][0] for i in live if vec[i]} - {'in', 'mul', 'inv', 'lin', 'sin', 'cos'})
    lanewise = [f'LIE_LANEWISE(lie_v{op}, {op})' for op in fns]   # sqrt, tanh, ...: the C library's, lane by lane
    table = ', '.join(str(v) for v in (n_sc, *(x for kp in sincos for x in kp)))
    return (_HEAD + '\n'.join(lanewise + lines + ['}']) + '\n'
            + f'const long lie_lanes_sincos[{1 + 2 * n_sc}] = {{{table}}};\n')


def _gather(arr, width, pos):
    """C initializer of a vector: value pos of LANES consecutive rows of `width` values at arr."""
    return '{' + ', '.join(f'{arr}[{l * width + pos}]' for l in range(LANES)) + '}'
