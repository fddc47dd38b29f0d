"""Looped native kernels: a traced algorithm's per-body steps, rendered once per step signature and
looped in C over the model's structure arrays (docs/architecture.md, "Looped native kernels").

A straight-line kernel (crender.py) is one C function per trace, every body's constants folded
in: its source, compile time and instruction footprint grow with the model (O(n) to O(n^3)). A
looped kernel is what the traced algorithm itself is: a loop over bodies calling one helper per
body and pass. `step` traces such a helper (the same function the straight-line trace calls,
e.g. traced/crba.py `composite`) on fresh symbols: the registers it reads and writes and the
body's constants become pointer arguments, so one C function serves every body of one step
signature (joint kind, coupling, which constants are exactly 0 or 1: those fold as in the
straight-line code). The family's driver (`lie_kernel`, same entry point and meta as a
straight-line kernel, so native.bind, batches, threads and `out=` run it unchanged) loops over
the bodies in tree order, or reversed, with the structure as static arrays: parents, the step
signature per body, the per-body constants and register offsets. Parameters (inertias and
payloads, gravity, locked-joint offsets, armature) stay run-time arguments: setters never
recompile. The library depends on the structure only, so the disk cache keys it by the model's
fingerprint and the kernel's name (native.library), with `:looped` appended.
"""
import numpy as np

from . import native as _native
from .crender import emit_step, literal
from .tracer import Graph

_HEAD = '#include <math.h>\n#include <stdlib.h>\n#include <string.h>\n'
# Registers of one call up to this many doubles live on the stack (32 KB: any thread's stack
# takes it), more in one malloc'ed block (~0.1 us, against >= 5 us for a call of that size).
STACK_DOUBLES = 4096


def step(name, fn, widths):
    """C text of step `name`: fn(g, *groups) -> list of output groups (lists of Syms or floats),
    traced on one group of fresh input symbols per entry of `widths` (crender.emit_step)."""
    g = Graph()
    names = [[f'{name}_{k}_{i}' for i in range(w)] for k, w in enumerate(widths)]
    outs = fn(g, *[[g.input(nm) for nm in ns] for ns in names])
    return emit_step(g, name, names, [list(o) for o in outs])


def classify(keys):
    """(the distinct step signatures in first-seen order, each body's index among them)."""
    seen = {}
    idx = [seen.setdefault(k, len(seen)) for k in keys]
    return list(seen), idx


def table(ctype, name, values):
    """A static const C array of the structure (ints or doubles; every bit of a double kept)."""
    vals = ', '.join(literal(v) if ctype == 'double' else str(int(v)) for v in values) or '0'
    return f'static const {ctype} {name}[] = {{{vals}}};\n'


def switch(var, names, call):
    """C text calling names[var](call): a switch over the step signatures (none for one)."""
    if len(names) == 1:
        return f'{names[0]}({call});'
    cases = ' '.join(f'case {i}: {nm}({call}); break;' for i, nm in enumerate(names))
    return f'switch ({var}) {{ {cases} }}'


def joints_of(fr):
    """Each body's joint index (-1: welded) when every joint moves one body with multiplier 1 (no
    mimic joints: the looped drivers index q by body), else None."""
    nz = fr.E != 0
    if np.any(nz.sum(axis=1) > 1) or np.any(fr.E[nz] != 1.0) or np.any(nz.sum(axis=0) != 1):
        return None
    return [int(np.flatnonzero(nz[b])[0]) if nz[b].any() else -1 for b in range(fr.nb)]


def offsets_of(fr):
    """Each body's index in the offsets parameter list (Frames.offsets), -1 without one."""
    out, k = [], 0
    for b in range(fr.nb):
        out.append(k if fr.offset[b] else -1)
        k += bool(fr.offset[b])
    return out


def structure(fr):
    """The C arrays every driver reads: NB, PAR (parents), JNT (joint per body), OFF (offset index
    per body), and the C expression X_OF(b) of body b's coordinate x_b = q_j + e_b (0 if welded)."""
    J, O = joints_of(fr), offsets_of(fr)
    return (f'#define NB {fr.nb}\n#define NJ {fr.n}\n' + table('int', 'PAR', fr.parent) + table('int', 'JNT', J)
            + table('int', 'OFF', O)
            + '#define X_OF(q, e0, b) ((JNT[b] >= 0 ? (q)[JNT[b]] : 0.0) + (OFF[b] >= 0 ? (e0)[OFF[b]] : 0.0))\n')


def work(arrays, n_out):
    """C text declaring the register arrays [(name, doubles)] of one call as pointers into one block
    (on the stack up to STACK_DOUBLES, else malloc'ed; out of memory: NaN outputs, which the call
    declines, and the reference answers), and the text freeing it at the end of the driver."""
    total = sum(n for _, n in arrays)
    if total <= STACK_DOUBLES:
        lines = [f'  double w_[{total}];']
        free = ''
    else:
        lines = [f'  double *w_ = malloc({total} * sizeof(double));',
                 f'  if (!w_) {{ for (int k = 0; k < {n_out}; k++) out[k] = NAN; return; }}']
        free = '  free(w_);\n'
    at = 0
    for name, n in arrays:
        lines.append(f'  double *const {name} = w_ + {at};')
        at += n
    return '\n'.join(lines) + '\n', free


def rendered(source, state_widths, par_lengths, n_out):
    """The native.Rendered of a looped kernel's C text (one translation unit)."""
    return _native.Rendered(_HEAD + source, tuple(state_widths), tuple(par_lengths), int(n_out))


def sym6_index():
    """Position of entry (i, j), i <= j, of a symmetric 6x6 stored as its 21 upper entries."""
    idx, k = {}, 0
    for i in range(6):
        for j in range(i, 6):
            idx[i, j] = idx[j, i] = k
            k += 1
    return idx


_S6 = sym6_index()


def sym6_in(vals):
    """A traced symmetric 6x6 (nested lists) from its 21 upper entries."""
    return [[vals[_S6[i, j]] for j in range(6)] for i in range(6)]


def sym6_out(K):
    """The 21 upper entries of a symmetric 6x6."""
    return [K[i][j] for i in range(6) for j in range(i, 6)]


def pose_in(v):
    """A traced pose (R, t) from 12 values: R row-major, then t."""
    return tuple(tuple(v[3 * r:3 * r + 3]) for r in range(3)), tuple(v[9:12])


def pose_out(X):
    """The 12 values of a pose (R, t): R row-major, then t."""
    return [e for row in X[0] for e in row] + list(X[1])


def exact(v):
    """A constant a step folds (0, 1 or -1, as the straight-line trace folds it), else None: a
    register of the step, so that bodies differing only there share one step."""
    v = float(v)
    return v + 0.0 if v in (0.0, 1.0, -1.0) else None


def dfs_order(fr):
    """The bodies in depth-first order (each parent before its children, a subtree contiguous):
    a driver keeping one register block per depth along the current path reuses it for the
    next subtree."""
    order, stack = [], [b for b in reversed(range(fr.nb)) if fr.parent[b] < 0]
    while stack:
        b = stack.pop()
        order.append(b)
        stack.extend(reversed(fr.children[b]))
    return order
