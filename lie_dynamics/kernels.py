"""Straight-line RNEA kernels generated per model (paper eqs 16-21), compiled once and cached.

Why: a numpy call costs ~0.5-1.5 us whatever its size, so one state pushed through a tree of
3x3 blocks is all call overhead, and stacked tiny matmuls waste most of their time too. Here
the recursion of eqs 18-21 is unrolled for the model's tree into plain arithmetic with the
constant home poses folded in (exact zeros and ones drop out), so only the flops the model
really needs remain. The same code is rendered twice:
  * for Python floats, one state (~11-15 ns per operation, no numpy call at all), and
  * for numpy rows, a chunk of states (state-last layout: every operation is one ufunc on
    contiguous rows writing into preallocated registers, its fixed cost shared by the chunk).

Frames: body frame b' is body frame b turned by a constant rotation Q_b that takes z to the
joint axis (the screw S_b is (a, 0) or (0, a) through the origin, so this is always possible).
Then f_{p',b'}(x) = M'_b Rz(x) or M'_b Trans(z x), S'_b = (e_z, 0) or (0, e_z), and
tau_b = S'_b^T F_b is one component of the wrench. Inertias are moved to the primed frames
as parameters, so payload, gravity and locked-joint changes never recompile.
"""
import math

import numpy as np

from .codegen import Frames

# Kernels for models larger than this are not generated (compile time grows with the
# source); callers fall back to the vectorised reference implementation.
MAX_BODIES = 256
# States per numpy pass: large enough that the ~0.5 us fixed cost of each ufunc is small
# next to its per-element work, small enough that the rows mostly stay in cache.
CHUNK = 4096
CHUNK_BYTES = 8 << 20  # cap on the rows a kernel keeps (smaller chunks for big models)


def supports(model):
    """True when every screw is a unit rotation axis or a unit translation (URDF joints)."""
    if model.nb > MAX_BODIES:
        return False
    w, v = model.S[:, :3], model.S[:, 3:]
    nw, nv = np.linalg.norm(w, axis=1), np.linalg.norm(v, axis=1)
    rev = (np.abs(nw - 1) < 1e-12) & (nv == 0)
    pri = (nw == 0) & (np.abs(nv - 1) < 1e-12)
    return bool(np.all(rev | pri))


class _Code:
    """Straight-line code with constant folding, rendered for floats or for numpy rows.

    A value is a float constant, a name, or '-name' (signs are carried, not computed).
    Names are scalars (model parameters, the same for every state) or rows (per-state
    values; numpy rows in the rows rendering). Each line defines one temporary: 't' rows,
    'u' scalars.
    """

    def __init__(self):
        self.lines = []  # (target, op, data): op 'sum' with (parts, const), or 'cos'/'sin' with a name
        self.scalars = set()
        self.k = 0

    def _new(self, scalar):
        name = f'{"u" if scalar else "t"}{self.k}'
        self.k += 1
        if scalar:
            self.scalars.add(name)
        return name

    def trig(self, fn, x):
        """cos(x) or sin(x) of a value."""
        if not isinstance(x, str):
            return getattr(math, fn)(x)
        neg = x[0] == '-'
        x = x.lstrip('-')
        name = self._new(x in self.scalars)
        self.lines.append((name, fn, x))
        return '-' + name if neg and fn == 'sin' else name

    def sum(self, terms):
        """sum(coef * f1 * f2 ...) for terms (coef, f1, ...); folds constant factors and zeros."""
        const, parts = 0.0, []
        for coef, *fs in terms:
            syms = []
            for f in fs:
                if isinstance(f, str):
                    if f[0] == '-':  # a negated name: keep the sign in the coefficient
                        coef, f = -coef, f[1:]
                    syms.append(f)
                else:
                    coef *= f
            if coef == 0.0:
                continue
            if syms:
                # scalar factors first: evaluated left to right, they multiply as floats
                parts.append((coef, sorted(syms, key=lambda y: y not in self.scalars)))
            else:
                const += coef
        if not parts:
            return const
        if len(parts) == 1 and const == 0.0 and abs(parts[0][0]) == 1.0 and len(parts[0][1]) == 1:
            return ('-' if parts[0][0] < 0 else '') + parts[0][1][0]
        sign = ''
        if all(c < 0 for c, _ in parts) and const <= 0.0:  # compute -sum, carry the sign
            parts, const, sign = [(-c, syms) for c, syms in parts], -const, '-'
        parts.sort(key=lambda p: p[0] < 0)  # a positive term first avoids a negation
        name = self._new(all(y in self.scalars for _, syms in parts for y in syms))
        self.lines.append((name, 'sum', (parts, const)))
        return sign + name

    # ---- 3-vector helpers (tuples of values) ----
    def lin(self, K, vec, add=None):
        """K @ vec (+ add) for a constant matrix K."""
        rows = []
        for j in range(K.shape[0]):
            terms = [(float(K[j, k]), vec[k]) for k in range(len(vec))]
            if add is not None:
                terms.append((1.0, add[j]))
            rows.append(self.sum(terms))
        return tuple(rows)

    def rz(self, c, s, u, transpose):
        """Rz(x) u, or Rz(x)^T u, with c = cos x, s = sin x."""
        sg = -1.0 if transpose else 1.0
        return (self.sum([(1.0, c, u[0]), (-sg, s, u[1])]),
                self.sum([(sg, s, u[0]), (1.0, c, u[1])]), u[2])

    def cross(self, a, b):
        return (self.sum([(1.0, a[1], b[2]), (-1.0, a[2], b[1])]),
                self.sum([(1.0, a[2], b[0]), (-1.0, a[0], b[2])]),
                self.sum([(1.0, a[0], b[1]), (-1.0, a[1], b[0])]))

    # ---- rendering
    def _registers(self, returns):
        """Row temporaries -> register names; a line's target never shares its operands' register
        (the numpy rendering writes the target while still reading operands)."""
        def uses(line):
            target, op, data = line
            return [data] if op != 'sum' else [y for _, syms in data[0] for y in syms]
        # drop dead lines (e.g. a product needed only with a factor that folded to zero)
        needed = {r.lstrip('-') for r in returns if isinstance(r, str)}
        live = []
        for line in reversed(self.lines):
            if line[0] in needed:
                live.append(line)
                needed.update(uses(line))
        self.lines = live[::-1]
        last = {}
        for i, line in enumerate(self.lines):
            for u in uses(line):
                last[u] = i
        for r in returns:
            if isinstance(r, str):
                last[r.lstrip('-')] = len(self.lines)
        regs, free, nreg = {}, [], 0
        for i, line in enumerate(self.lines):
            target = line[0]
            if target[0] == 't':
                if free:
                    regs[target] = free.pop()
                else:
                    regs[target], nreg = f'r{nreg}', nreg + 1
                if target not in last:
                    free.append(regs[target])
            for u in set(uses(line)):
                if last[u] == i and u in regs:
                    free.append(regs[u])
        return regs, nreg

    def source(self, name, args, returns, header):
        """(float source, numpy-rows source, register count) of the function.

        The rows version takes one more argument, B: nreg + 1 preallocated rows it writes in
        place (ufunc out=), so a chunk allocates nothing (allocation churn of large temporaries
        costs page faults when the allocator trims its heap).
        """
        regs, nreg = self._registers(returns)

        def ren(y):
            return regs.get(y, y)

        def expr(parts, const):
            out = []
            for i, (coef, syms) in enumerate(parts):
                body = '*'.join(ren(y) for y in syms)
                if abs(coef) != 1.0:
                    body = f'{abs(coef)!r}*{body}'
                out.append(('-' if coef < 0 else ('+' if i else '')) + body)
            if const != 0.0:
                out.append(f'{"-" if const < 0 else "+"}{abs(const)!r}')
            return ''.join(out)

        flt, rows = [], []
        for target, op, data in self.lines:
            t = ren(target)
            if op == 'sum':
                e = expr(*data)
                flt.append(f'{t} = {e}')
                rows.extend([f'{t} = {e}'] if target in self.scalars else
                            _rows_sum(t, data[0], data[1], ren, lambda y: y not in self.scalars))
            else:
                flt.append(f'{t} = {op}({ren(data)})')
                rows.append(f'{t} = {op}({ren(data)})' if target in self.scalars else f'{op}({ren(data)}, {t})')
        rets = ', '.join(ren(r.lstrip('-')).join(('-' if r[0] == '-' else '', ''))
                         if isinstance(r, str) else repr(r) for r in returns)
        head = ''.join(header)
        ret = f'    return ({rets},)\n'
        f_src = f'def {name}({", ".join(args)}):\n' + head + ''.join(f'    {x}\n' for x in flt) + ret
        regs_unpack = _unpack([f'r{k}' for k in range(nreg)] + ['TMP'], 'B')
        r_src = (f'def {name}({", ".join(args + ["B"])}):\n' + head + regs_unpack
                 + ''.join(f'    {x}\n' for x in rows) + ret)
        return f_src, r_src, nreg


def _rows_sum(R, parts, const, ren, isrow):
    """In-place numpy statements computing sum(parts) + const into row R (scratch row TMP)."""
    def scal(c, names):  # Python expression of the scalar factor, None when it is 1
        if not names:
            return None if c == 1.0 else repr(c)
        e = '*'.join(names)
        return e if c == 1.0 else ('-' + e if c == -1.0 else f'{c!r}*{e}')

    terms, cexpr = [], [repr(const)] if const != 0.0 else []
    for coef, syms in parts:
        rs, ss = [ren(y) for y in syms if isrow(y)], [ren(y) for y in syms if not isrow(y)]
        if rs:
            terms.append((coef, rs, ss))
        else:  # a scalar term joins the constant
            cexpr.append(scal(coef, ss))
    cexpr = '+'.join(cexpr) if cexpr else None

    def plain(t):
        return len(t[1]) == 1 and not t[2] and abs(t[0]) == 1.0

    terms.sort(key=lambda t: (plain(t), t[0] < 0))
    out, negate = [], False
    first = terms[0]
    if not plain(first):
        c, rs, ss = first
        if len(rs) == 1:
            out.append(f'mul({rs[0]}, {scal(c, ss)}, {R})')
        else:
            out.append(f'mul({rs[0]}, {rs[1]}, {R})')
            out.extend(f'{R} *= {r}' for r in rs[2:])
            if c == -1.0 and not ss:
                out.append(f'neg({R}, {R})')
            elif scal(c, ss) is not None:
                out.append(f'{R} *= {scal(c, ss)}')
        rest = terms[1:]
    elif len(terms) >= 2:
        (c1, (a,), _), (c2, (b,), _) = terms[0], terms[1]
        negate = c1 < 0  # all plain terms negative: sum them, negate once
        out.append(f'{"add" if c1 * c2 > 0 else "sub"}({a}, {b}, {R})')
        rest = terms[2:]
    else:
        c1, (a,), _ = first
        out.append(f'add({a}, {cexpr}, {R})' if c1 > 0 else f'sub({cexpr}, {a}, {R})')
        return out
    for c, rs, ss in rest:
        sign = '-' if (c < 0) != negate else '+'
        if plain((c, rs, ss)):
            out.append(f'{R} {sign}= {rs[0]}')
            continue
        if len(rs) == 1:
            out.append(f'mul({rs[0]}, {scal(abs(c), ss)}, TMP)')
        else:
            out.append(f'mul({rs[0]}, {rs[1]}, TMP)')
            out.extend(f'TMP *= {r}' for r in rs[2:])
            if scal(abs(c), ss) is not None:
                out.append(f'TMP *= {scal(abs(c), ss)}')
        out.append(f'{R} {sign}= TMP')
    if negate:
        out.append(f'neg({R}, {R})')
    if cexpr is not None:
        out.append(f'{R} += {cexpr}')
    return out


def _unpack(names, src):
    return f'    {", ".join(names)}{"," if len(names) == 1 else ""} = {src}\n'


class Structure(Frames):
    """Constant per-model data shared by all kernels: the primed frames of codegen.Frames
    (every joint axis is z; the home poses M'_b = (R0, p0) folded in) and Ad_{M'^-1}."""

    def __init__(self, model):
        super().__init__(model)
        self.R0 = [np.array(R) for R in self.R]
        self.p0 = [np.array(t) for t in self.t]
        # Ad_{M'^-1} = [[R'^T, 0], [-R'^T [p'], R'^T]]
        self.K = []
        for R, t in zip(self.R0, self.p0):
            P = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
            K = np.zeros((6, 6))
            K[:3, :3] = K[3:, 3:] = R.T
            K[3:, :3] = -R.T @ P
            self.K.append(K)

    def gravity_params(self, J):
        """Per body (subtree mass, h_b + sum over children of m_sub p'_c): 4 floats."""
        m = J[:, 3, 3].copy()
        h = self.inertia_table(J)[:, 1:4].copy()
        for b in range(self.nb - 1, -1, -1):  # children have larger indices
            for c in self.children[b]:
                m[b] += m[c]
                h[b] += m[c] * self.p0[c]
        return np.column_stack([m, h])

    # ---- code generation
    def _coordinates(self, C, header, order):
        """Body coordinates x = E q + e0 and their rates, plus sin/cos of revolute ones."""
        n, nb = self.n, self.nb
        header.append(_unpack([f'q{j}' for j in range(n)], 'Q'))
        if order >= 1:
            header.append(_unpack([f'qv{j}' for j in range(n)], 'QD'))
            header.append(_unpack([f'qa{j}' for j in range(n)], 'QDD'))
        off = [b for b in range(nb) if self.offset[b]]
        if off:
            header.append(_unpack([f'e{b}' for b in off], 'E0'))
            C.scalars.update(f'e{b}' for b in off)
        x, xd, xdd, cs = [], [], [], []
        for b in range(nb):
            terms = [(float(self.E[b, j]), f'q{j}') for j in range(n)]
            if self.offset[b]:
                terms.append((1.0, f'e{b}'))
            x.append(C.sum(terms))
            if order >= 1:
                xd.append(C.sum([(float(self.E[b, j]), f'qv{j}') for j in range(n)]))
                xdd.append(C.sum([(float(self.E[b, j]), f'qa{j}') for j in range(n)]))
            if self.revolute[b]:
                xb = x[b]
                cs.append((C.trig('cos', xb), C.trig('sin', xb)))
            else:
                cs.append(None)
        return x, xd, xdd, cs

    def _torques(self, C, tau_b):
        return [C.sum([(float(self.E[b, j]), tau_b[b]) for b in range(self.nb)]) for j in range(self.n)]

    def inverse_dynamics_source(self, wrench):
        """Source of k(Q, QD, QDD, P, A0, E0[, FX]) -> tau tuple (eqs 18-21 in primed frames)."""
        C = _Code()
        header = []
        x, xd, xdd, cs = self._coordinates(C, header, 1)
        nb = self.nb
        params = [[f'{k}{b}' for k in ('m', 'hx', 'hy', 'hz', 'ixx', 'ixy', 'ixz', 'iyy', 'iyz', 'izz')]
                  for b in range(nb)]
        header.append(_unpack([p for ps in params for p in ps], 'P'))
        header.append(_unpack(['g0', 'g1', 'g2'], 'A0'))
        C.scalars.update([p for ps in params for p in ps] + ['g0', 'g1', 'g2'])
        if wrench:
            header.append(_unpack([f'f{b}_{k}' for b in range(nb) for k in range(6)], 'FX'))
        V, Vd, F = [None] * nb, [None] * nb, [None] * nb
        zero = (0.0, 0.0, 0.0)
        for b in range(nb):
            p = self.parent[b]
            Vp = V[p] if p >= 0 else zero + zero
            Vdp = Vd[p] if p >= 0 else zero + ('g0', 'g1', 'g2')
            K = self.K[b]
            U, Ud = C.lin(K, Vp), C.lin(K, Vdp)              # Ad_{M'^-1} V_{i-1}
            if self.revolute[b]:
                c, s = cs[b]
                w = C.rz(c, s, U[:3], True)
                w = (w[0], w[1], C.sum([(1.0, w[2]), (1.0, xd[b])]))           # eq 18
                v = C.rz(c, s, U[3:], True)
                wd = C.rz(c, s, Ud[:3], True)
                vd = C.rz(c, s, Ud[3:], True)
                # eq 19: + S xdd + ad_{V_i}(S xd); ad_V(e_z xd, 0) = (w x e_z xd, v x e_z xd)
                wd = (C.sum([(1.0, wd[0]), (1.0, w[1], xd[b])]), C.sum([(1.0, wd[1]), (-1.0, w[0], xd[b])]),
                      C.sum([(1.0, wd[2]), (1.0, xdd[b])]))
                vd = (C.sum([(1.0, vd[0]), (1.0, v[1], xd[b])]), C.sum([(1.0, vd[1]), (-1.0, v[0], xd[b])]), vd[2])
            else:
                xb = x[b]
                # Ad_{Trans(z x)^-1}: v += x (w_y, -w_x, 0); then S xd = (0, e_z xd)
                w = U[:3]
                v = (C.sum([(1.0, U[3]), (1.0, xb, w[1])]), C.sum([(1.0, U[4]), (-1.0, xb, w[0])]),
                     C.sum([(1.0, U[5]), (1.0, xd[b])]))
                wd = Ud[:3]
                # eq 19: ad_V(0, e_z xd) = (0, w x e_z xd)
                vd = (C.sum([(1.0, Ud[3]), (1.0, xb, wd[1]), (1.0, w[1], xd[b])]),
                      C.sum([(1.0, Ud[4]), (-1.0, xb, wd[0]), (-1.0, w[0], xd[b])]),
                      C.sum([(1.0, Ud[5]), (1.0, xdd[b])]))
            V[b], Vd[b] = w + v, wd + vd
            # eq 20, body term J Vd - ad*_V (J V) with J = [[I_o, [h]], [-[h], m]], rewritten with
            # the Jacobi identity (fewer products, same value): with a = vd + w x v,
            #   n = I_o wd + w x (I_o w) + h x a,   f = m a + wd x h + w x (w x h)
            m, hx, hy, hz, ixx, ixy, ixz, iyy, iyz, izz = params[b]
            h = (hx, hy, hz)
            I = ((ixx, ixy, ixz), (ixy, iyy, iyz), (ixz, iyz, izz))
            X = ((1, 2), (2, 0), (0, 1))  # (u x v)_r = u[j] v[k] - u[k] v[j]
            acc = tuple(C.sum([(1.0, vd[r]), (1.0, w[j], v[k]), (-1.0, w[k], v[j])]) for r, (j, k) in enumerate(X))
            Iw = tuple(C.sum([(1.0, I[r][k], w[k]) for k in range(3)]) for r in range(3))
            wh = tuple(C.sum([(1.0, w[j], h[k]), (-1.0, w[k], h[j])]) for j, k in X)
            Fn = [C.sum([(1.0, I[r][k], wd[k]) for k in range(3)]
                        + [(1.0, w[j], Iw[k]), (-1.0, w[k], Iw[j]), (1.0, h[j], acc[k]), (-1.0, h[k], acc[j])])
                  for r, (j, k) in enumerate(X)]
            Ff = [C.sum([(1.0, m, acc[r]), (1.0, wd[j], h[k]), (-1.0, wd[k], h[j]), (1.0, w[j], wh[k]),
                         (-1.0, w[k], wh[j])]) for r, (j, k) in enumerate(X)]
            if wrench:
                Fn = [C.sum([(1.0, Fn[r]), (-1.0, f'f{b}_{r}')]) for r in range(3)]
                Ff = [C.sum([(1.0, Ff[r]), (-1.0, f'f{b}_{r + 3}')]) for r in range(3)]
            F[b] = Fn + Ff
        tau_b = [None] * nb
        for b in range(nb - 1, -1, -1):                        # backward pass, eqs 20-21
            Fb = F[b]
            tau_b[b] = Fb[2] if self.revolute[b] else Fb[5]
            p = self.parent[b]
            if p < 0:
                continue
            if self.revolute[b]:
                c, s = cs[b]
                G = C.rz(c, s, Fb[:3], False) + C.rz(c, s, Fb[3:], False)
            else:  # Ad*_{Trans(z x)}: n += (z x) x f
                xb = x[b]
                G = (C.sum([(1.0, Fb[0]), (-1.0, xb, Fb[4])]), C.sum([(1.0, Fb[1]), (1.0, xb, Fb[3])]), Fb[2]) \
                    + tuple(Fb[3:])
            F[p] = list(C.lin(self.K[b].T, G, add=F[p]))       # Ad*_{M'^-1} = K^T
        tau = self._torques(C, tau_b)
        args = ['Q', 'QD', 'QDD', 'P', 'A0', 'E0'] + (['FX'] if wrench else [])
        return C.source('inverse_dynamics_kernel', args, tau, header)

    def gravity_source(self):
        """Source of k(Q, P, A0, E0) -> g(q) tuple.

        With V = 0 and Vdot_0 = (0, -g), eq 19 leaves only the linear acceleration a_i = R^T a_p,
        and the subtree sum of eq 20 is (H_i x a_i, m_i a_i): subtree mass m_i (a parameter)
        and first moment H_i = h'_i + sum_c (R_c H_c + m_c p_c), its constant part folded into
        the parameters. Eq 21 is then one component.
        """
        C = _Code()
        header = []
        x, _, _, cs = self._coordinates(C, header, 0)
        nb = self.nb
        params = [[f'm{b}', f'hx{b}', f'hy{b}', f'hz{b}'] for b in range(nb)]
        header.append(_unpack([p for ps in params for p in ps], 'P'))
        header.append(_unpack(['g0', 'g1', 'g2'], 'A0'))
        C.scalars.update([p for ps in params for p in ps] + ['g0', 'g1', 'g2'])
        acc = [None] * nb
        for b in range(nb):
            p = self.parent[b]
            ap = acc[p] if p >= 0 else ('g0', 'g1', 'g2')
            u = C.lin(self.R0[b].T, ap)
            acc[b] = C.rz(*cs[b], u, True) if self.revolute[b] else u
        H = [tuple(ps[1:]) for ps in params]
        tau_b = [None] * nb
        for b in range(nb - 1, -1, -1):
            a = acc[b]
            if self.revolute[b]:
                tau_b[b] = C.sum([(1.0, H[b][0], a[1]), (-1.0, H[b][1], a[0])])
            else:
                tau_b[b] = C.sum([(1.0, params[b][0], a[2])])
            p = self.parent[b]
            if p < 0:
                continue
            if self.revolute[b]:
                u = C.rz(*cs[b], H[b], False)
            else:  # H + m_sub z x
                u = (H[b][0], H[b][1], C.sum([(1.0, H[b][2]), (1.0, params[b][0], x[b])]))
            H[p] = C.lin(self.R0[b], u, add=H[p])
        tau = self._torques(C, tau_b)
        return C.source('gravity_kernel', ['Q', 'P', 'A0', 'E0'], tau, header)


_FLOAT_NS = {'sin': math.sin, 'cos': math.cos, '__builtins__': {}}
_ROWS_NS = {'sin': np.sin, 'cos': np.cos, 'mul': np.multiply, 'add': np.add, 'sub': np.subtract,
            'neg': np.negative, '__builtins__': {}}


def compile_kernel(sources, filename):
    """(float function, rows function) from the two renderings of a kernel."""
    out = []
    for src, ns in zip(sources, (_FLOAT_NS, _ROWS_NS)):
        env = dict(ns)
        exec(compile(src, filename, 'exec'), env)
        out.append(next(v for k, v in env.items() if k.endswith('_kernel')))
    return tuple(out)


class Kernels:
    """Per-model cache: the structure, lazily compiled kernels and their parameter tuples."""

    def __init__(self, model):
        self.structure = Structure(model)
        self._fns, self._regs, self._pool = {}, {}, {}
        self._params, self._row_params = (None, None), None

    def function(self, kind):
        """(scalar, numpy) versions of kernel `kind`: 'id', 'id_wrench' or 'gravity'."""
        fns = self._fns.get(kind)
        if fns is None:
            st = self.structure
            fsrc, rsrc, regs = (st.gravity_source() if kind == 'gravity'
                                else st.inverse_dynamics_source(kind == 'id_wrench'))
            fns = self._fns[kind] = compile_kernel((fsrc, rsrc), f'<lie_dynamics {kind} kernel>')
            self._regs[kind] = regs
        return fns

    def rows(self, kind, inputs):
        """Run the rows kernel `kind` over batches; yields (slice, outputs) chunk by chunk.

        inputs: (N, k) arrays; each chunk is copied, transposed, into state-last input rows.
        The rows (inputs, registers, scratch; about CHUNK_BYTES) are reused across chunks and
        calls, so a call allocates nothing per operation and touches no fresh pages. They
        come from a pool, so concurrent callers never share them.
        """
        fn = self.function(kind)[1]
        N = inputs[0].shape[0]
        widths = [a.shape[1] for a in inputs]
        regs = self._regs[kind] + 1
        rows = regs + sum(widths)
        size = int(min(CHUNK, max(256, CHUNK_BYTES // (8 * rows))))
        pool = self._pool.setdefault(kind, [])
        try:
            buf = pool.pop()
        except IndexError:
            buf = np.empty((rows, size))
        try:
            for start in range(0, N, size):
                stop = min(N, start + size)
                view = buf[:, :stop - start]
                args, r = [], regs
                for a, w in zip(inputs, widths):
                    view[r:r + w] = a[start:stop].T
                    args.append(view[r:r + w])
                    r += w
                yield slice(start, stop), fn, args, list(view[:regs])
        finally:
            pool.append(buf)

    def params(self, model):
        """(inverse-dynamics P, gravity P, base acceleration, offsets), refreshed on change.

        The model replaces (never mutates) J, _a0 and e0 in its setters, so identity tells.
        """
        key, values = self._params
        if key is None or not (key[0] is model.J and key[1] is model._a0 and key[2] is model.e0):
            st = self.structure
            values = (tuple(st.inertia_params(model.J)),
                      tuple(st.gravity_params(model.J).ravel().tolist()),
                      tuple(model._a0[3:].tolist()), tuple(st.offsets(model.e0)))
            self._params = ((model.J, model._a0, model.e0), values)  # one assignment: thread-safe
            self._row_params = None
        return values

    def row_params(self, model):
        """params() as 0-d arrays, for the rows kernels: a ufunc takes a 0-d array operand
        ~0.25 us faster than a Python float (no scalar conversion per call)."""
        values = self.params(model)
        rows = self._row_params
        if rows is None or rows[0] is not values:
            rows = self._row_params = (values, tuple(tuple(np.array(v) for v in vs) for vs in values))
        return rows[1]

    def __reduce__(self):
        # generated functions cannot be pickled: a copied model rebuilds its kernels on first use
        return type(None), ()


def for_model(model):
    """The model's Kernels, created on first use; None when the model is not supported."""
    k = model.__dict__.get('_kernels')
    if k is None:
        k = model._kernels = Kernels(model) if supports(model) else False
    return k or None
