"""Straight-line RNEA kernels generated per model (paper eqs 16-21), compiled once and cached.

Why: a numpy call costs ~0.5-1.5 us whatever its size, so one state pushed through a tree of
3x3 blocks is all call overhead, and stacked tiny matmuls waste most of their time too. Here
the recursion of eqs 18-21 is unrolled for the model's tree into plain arithmetic with the
constant home poses folded in (exact zeros and ones drop out), so only the flops the model
really needs remain. The recursion is written on scalars and traced by codegen.py (as the
other generated kernels are), which renders it twice:
  * for Python floats, one state (~11-15 ns per operation, no numpy call at all), and
  * for numpy rows, a chunk of states (state-last layout: every operation is one ufunc on
    contiguous rows writing into preallocated registers, its fixed cost shared by the chunk).
This module keeps what is particular to the RNEA: its two algorithms (inverse dynamics, and
gravity from subtree masses and first moments), their parameters, and the reusable row
buffers of the batched calls.

Frames: body frame b' is body frame b turned by a constant rotation Q_b that takes z to the
joint axis (the screw S_b is (a, 0) or (0, a) through the origin, so this is always possible).
Then f_{p',b'}(x) = M'_b Rz(x) or M'_b Trans(z x), S'_b = (e_z, 0) or (0, e_z), and
tau_b = S'_b^T F_b is one component of the wrench. Inertias are moved to the primed frames
as parameters, so payload, gravity and locked-joint changes never recompile.
"""
import numpy as np

from .. import codegen as cg
from . import Frames

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


def _lin(K, vec, add=None):
    """K @ vec (+ add) for a constant matrix K: zero entries fold away."""
    out = []
    for j in range(K.shape[0]):
        acc = add[j] if add is not None else 0.0
        for k in range(len(vec)):
            c = float(K[j, k])
            if c != 0.0:
                acc = acc + c * vec[k]
        out.append(acc)
    return tuple(out)


def _rz(c, s, u, transpose):
    """Rz(x) u, or Rz(x)^T u, with c = cos x, s = sin x."""
    if transpose:
        return (c * u[0] + s * u[1], c * u[1] - s * u[0], u[2])
    return (c * u[0] - s * u[1], s * u[0] + c * u[1], u[2])


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

    # ---- code generation (traced by codegen: straight-line code for floats and for numpy rows)
    def _trace_coordinates(self, g, rates):
        co = self.trace_coordinates(g, rates=rates)
        cs = [(g.cos(x), g.sin(x)) if rev else None for x, rev in zip(co['x'], self.revolute)]
        return co, cs

    def _torques(self, tau_b):
        return [sum((float(self.E[b, j]) * tau_b[b] for b in range(self.nb) if self.E[b, j] != 0), 0.0)
                for j in range(self.n)]

    def inverse_dynamics_kernel(self, wrench):
        """k(Q, QD, QDD, P, A0, E0[, FX]) -> tau tuple (eqs 18-21 in primed frames), as
        codegen.kernel: the float function with the rows function as its attribute."""
        g = cg.Graph()
        co, cs = self._trace_coordinates(g, 2)
        x, xd, xdd = co['x'], co['xd'], co['xdd']
        nb = self.nb
        parg, params = self.trace_params(g)
        ga = tuple(g.input(f'g{k}') for k in range(3))
        args = co['args'] + [parg, ('A0', ['g0', 'g1', 'g2']), co['offset_args']]
        if wrench:
            names = [f'f{b}_{k}' for b in range(nb) for k in range(6)]
            args.append(('FX', names))
            fx = [g.input(nm) for nm in names]
        V, Vd, F = [None] * nb, [None] * nb, [None] * nb
        zero = (0.0, 0.0, 0.0)
        for b in range(nb):
            p = self.parent[b]
            Vp = V[p] if p >= 0 else zero + zero
            Vdp = Vd[p] if p >= 0 else zero + ga
            K = self.K[b]
            U, Ud = _lin(K, Vp), _lin(K, Vdp)              # Ad_{M'^-1} V_{i-1}
            if self.revolute[b]:
                c, s = cs[b]
                w = _rz(c, s, U[:3], True)
                w = (w[0], w[1], w[2] + xd[b])                                     # eq 18
                v = _rz(c, s, U[3:], True)
                wd = _rz(c, s, Ud[:3], True)
                vd = _rz(c, s, Ud[3:], True)
                # eq 19: + S xdd + ad_{V_i}(S xd); ad_V(e_z xd, 0) = (w x e_z xd, v x e_z xd)
                wd = (wd[0] + w[1] * xd[b], wd[1] - w[0] * xd[b], wd[2] + xdd[b])
                vd = (vd[0] + v[1] * xd[b], vd[1] - v[0] * xd[b], vd[2])
            else:
                xb = x[b]
                # Ad_{Trans(z x)^-1}: v += x (w_y, -w_x, 0); then S xd = (0, e_z xd)
                w = U[:3]
                v = (U[3] + xb * w[1], U[4] - xb * w[0], U[5] + xd[b])
                wd = Ud[:3]
                # eq 19: ad_V(0, e_z xd) = (0, w x e_z xd)
                vd = (Ud[3] + xb * wd[1] + w[1] * xd[b], Ud[4] - xb * wd[0] - w[0] * xd[b], Ud[5] + xdd[b])
            V[b], Vd[b] = w + v, wd + vd
            # eq 20, body term J Vd - ad*_V (J V) with J = [[I_o, [h]], [-[h], m]], rewritten with
            # the Jacobi identity (fewer products, same value): with a = vd + w x v,
            #   n = I_o wd + w x (I_o w) + h x a,   f = m a + wd x h + w x (w x h)
            m, h, (ixx, ixy, ixz, iyy, iyz, izz) = params[b]
            I = ((ixx, ixy, ixz), (ixy, iyy, iyz), (ixz, iyz, izz))
            acc = cg.vadd(vd, cg.cross(w, v))
            Iw = cg.sym_vec((ixx, ixy, ixz, iyy, iyz, izz), w)
            wh = cg.cross(w, h)
            Fn = cg.vadd(cg.vadd(tuple(I[r][0] * wd[0] + I[r][1] * wd[1] + I[r][2] * wd[2] for r in range(3)),
                                 cg.cross(w, Iw)), cg.cross(h, acc))
            Ff = cg.vadd(cg.vadd(cg.vscale(m, acc), cg.cross(wd, h)), cg.cross(w, wh))
            if wrench:
                Fn = cg.vsub(Fn, fx[6 * b:6 * b + 3])
                Ff = cg.vsub(Ff, fx[6 * b + 3:6 * b + 6])
            F[b] = list(Fn) + list(Ff)
        tau_b = [None] * nb
        for b in range(nb - 1, -1, -1):                        # backward pass, eqs 20-21
            Fb = F[b]
            tau_b[b] = Fb[2] if self.revolute[b] else Fb[5]
            p = self.parent[b]
            if p < 0:
                continue
            if self.revolute[b]:
                c, s = cs[b]
                G = _rz(c, s, Fb[:3], False) + _rz(c, s, Fb[3:], False)
            else:  # Ad*_{Trans(z x)}: n += (z x) x f
                xb = x[b]
                G = (Fb[0] - xb * Fb[4], Fb[1] + xb * Fb[3], Fb[2]) + tuple(Fb[3:])
            F[p] = list(_lin(self.K[b].T, G, add=F[p]))       # Ad*_{M'^-1} = K^T
        return cg.kernel(g, 'inverse_dynamics_kernel', args, self._torques(tau_b))[0]

    def gravity_kernel(self):
        """k(Q, P, A0, E0) -> g(q) tuple, P = gravity_params (as inverse_dynamics_kernel).

        With V = 0 and Vdot_0 = (0, -g), eq 19 leaves only the linear acceleration a_i = R^T a_p,
        and the subtree sum of eq 20 is (H_i x a_i, m_i a_i): subtree mass m_i (a parameter)
        and first moment H_i = h'_i + sum_c (R_c H_c + m_c p_c), its constant part folded into
        the parameters. Eq 21 is then one component.
        """
        g = cg.Graph()
        co, cs = self._trace_coordinates(g, 0)
        x = co['x']
        nb = self.nb
        names = [f'p{b}_{k}' for b in range(nb) for k in range(4)]
        syms = [g.input(nm) for nm in names]
        params = [syms[4 * b:4 * b + 4] for b in range(nb)]
        ga = tuple(g.input(f'g{k}') for k in range(3))
        args = co['args'] + [('P', names), ('A0', ['g0', 'g1', 'g2']), co['offset_args']]
        acc = [None] * nb
        for b in range(nb):
            p = self.parent[b]
            u = _lin(self.R0[b].T, acc[p] if p >= 0 else ga)
            acc[b] = _rz(*cs[b], u, True) if self.revolute[b] else u
        H = [tuple(ps[1:]) for ps in params]
        tau_b = [None] * nb
        for b in range(nb - 1, -1, -1):
            a = acc[b]
            tau_b[b] = H[b][0] * a[1] - H[b][1] * a[0] if self.revolute[b] else params[b][0] * a[2]
            p = self.parent[b]
            if p < 0:
                continue
            if self.revolute[b]:
                u = _rz(*cs[b], H[b], False)
            else:  # H + m_sub z x
                u = (H[b][0], H[b][1], H[b][2] + params[b][0] * x[b])
            H[p] = _lin(self.R0[b], u, add=H[p])
        return cg.kernel(g, 'gravity_kernel', args, self._torques(tau_b))[0]


class Kernels:
    """Per-model cache: the structure, lazily compiled kernels and their parameter tuples."""

    def __init__(self, model):
        self.structure = Structure(model)
        self._fns, self._regs, self._pool = {}, {}, {}
        self._params, self._row_params = (None, None), None

    def function(self, kind):
        """The generated kernel `kind` (float function; cg.rows_function gives its rows form):
        'id', 'id_wrench' or 'gravity'."""
        fn = self._fns.get(kind)
        if fn is None:
            st = self.structure
            fn = st.gravity_kernel() if kind == 'gravity' else st.inverse_dynamics_kernel(kind == 'id_wrench')
            self._regs[kind] = fn.nreg
            self._fns[kind] = fn
        return fn

    def rows(self, kind, inputs):
        """Run the rows kernel `kind` over batches; yields (slice, outputs) chunk by chunk.

        inputs: (N, k) arrays; each chunk is copied, transposed, into state-last input rows.
        The rows (inputs, registers, scratch; about CHUNK_BYTES) are reused across chunks and
        calls, so a call allocates nothing per operation and touches no fresh pages. They
        come from a pool, so concurrent callers never share them.
        """
        fn = cg.rows_function(self.function(kind))
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
        if key is None or not (key[0] is model.J and key[1] is model.base_acceleration and key[2] is model.e0):
            st = self.structure
            values = (tuple(st.inertia_params(model.J)),
                      tuple(st.gravity_params(model.J).ravel().tolist()),
                      tuple(model.base_acceleration[3:].tolist()), tuple(st.offsets(model.e0)))
            self._params = ((model.J, model.base_acceleration, model.e0), values)  # one assignment: thread-safe
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
