"""The composite rigid body algorithm, traced (the recursive form of eq 39; algorithms/crba.py)."""
from .. import algebra as la
from .. import looped
from ..frames import joint_transform
from ..kernel import Trace
from ..runtime import Spec
from ..tracer import Graph


# The steps of the CRBA, per body (the straight-line trace below and the looped kernel,
# looped.py, both call them): the composite-inertia update, the joint's wrench, its component
# along the joint axis; the ancestor walk is algebra.wrench_to_parent.
def composite(ic_b, X_b, ic_p):
    """ic_p plus the composite inertia ic_b of a child moved to the parent frame by X_b = (R, t)."""
    m, h, Io = la.inertia_to_parent(ic_b, *X_b)
    mp, hp, Ip = ic_p
    return (mp + m, la.vadd(hp, h), la.vadd(Ip, Io))


def joint_wrench(revolute, ic):
    """F = Jc_b S_b for the composite inertia ic = (m, h, I) and the primed axis S_b."""
    m, h, Io = ic
    if revolute:
        return ((Io[2], Io[4], Io[5]), (-h[1], h[0], 0.0))
    return ((h[1], -h[0], 0.0), (0.0, 0.0, m))


def s_dot(revolute, F):
    """S_j^T F for a wrench F = (n, f) in frame j'."""
    return F[0][2] if revolute else F[1][2]


def trace_mass_matrix(fr, g, params, X, armature):
    """Traced joint-space M (nested n x n lists) by the composite rigid body algorithm, with
    the armature (one symbol per joint, Frames.trace_armature) on its diagonal.

    In the primed body frames (codegen/frames.py), with X the traced joint transforms:
    backward, Jc_parent += (inertia of the subtree of b, moved to the parent frame); then for
    each joint b: F = Jc_b S_b, m_bb = S_b^T F, and F carried to every ancestor j
    (F <- Ad*_{f^-1} F) gives m_jb = S_j^T F.
    """
    nb = fr.nb
    ic = list(params)
    for b in reversed(range(nb)):
        p = fr.parent[b]
        if p >= 0:
            ic[p] = composite(ic[b], X[b], ic[p])
    Mx = [[0.0] * nb for _ in range(nb)]
    for b in range(nb):
        F = joint_wrench(fr.revolute[b], ic[b])
        Mx[b][b] = s_dot(fr.revolute[b], F)
        j = b
        while fr.parent[j] >= 0:
            F = la.wrench_to_parent(F, *X[j])
            j = fr.parent[j]
            Mx[j][b] = Mx[b][j] = s_dot(fr.revolute[j], F)
    Mq = fr.project(Mx)
    n = fr.n
    return [[Mq[a][a] + armature[a] if a == c else Mq[min(a, c)][max(a, c)] for c in range(n)] for a in range(n)]


def build_mass_matrix(fr):
    """k(Q, P, E0, AR) -> M row-major."""
    g = Graph()
    co = fr.trace_coordinates(g)
    parg, params = fr.trace_params(g)
    ararg, arm = fr.trace_armature(g)
    X = [fr.joint_transform(g, b, co['x'][b]) for b in range(fr.nb)]
    M = trace_mass_matrix(fr, g, params, X, arm)
    outputs = [v for row in M for v in row]
    return Trace(g, 'mass_kernel', co['args'] + [parg, co['offset_args'], ararg], outputs)


# ---------------------------------------------------------------------------- looped form
def _ic(v):
    return v[0], tuple(v[1:4]), tuple(v[4:10])


def _ic_flat(ic):
    return [ic[0], *ic[1], *ic[2]]


def _F_flat(F):
    return [*F[0], *F[1]]


def looped_mass_matrix(fr):
    """The looped native form of MASS_MATRIX (codegen/looped.py), or None (mimic joints): the
    driver of `looped_mass_pass`."""
    if looped.joints_of(fr) is None:
        return None
    decl, free = looped.work([('X', 12 * fr.nb), ('IC', 10 * fr.nb)], fr.n * fr.n)
    src = [looped.structure(fr), looped_mass_pass(fr), f'''
void lie_kernel(const double *const *in, const double *const *par, double *out)
{{
{decl}  crba_pass(in[0], par[0], par[1], par[2], X, IC, out);
{free}}}
''']
    return looped.rendered(''.join(src), (fr.n,), (10 * fr.nb, sum(fr.offset), fr.n), fr.n * fr.n)


def looped_mass_pass(fr):
    """C text of `static void crba_pass(q, P, E0, AR, X, IC, M)`: the CRBA's looped passes writing
    M (NJ x NJ, row-major; q is read before M is written, so M may alias it), with registers X (12
    per body: the joint transforms) and IC (10 per body), after looped.structure's arrays. Steps:
    the joint transform (frames.joint_transform, per joint kind), `composite` (backward), the
    joint wrench (`joint_wrench`, per joint kind) and the ancestor walk (algebra.wrench_to_parent,
    one step for every pair); the pass writes S_j^T F (`s_dot`: component 2 or 5 of F) into M. For
    the mass matrix's driver and the forward-dynamics derivatives' (traced/derivatives.py)."""
    kinds, sig = looped.classify(list(fr.revolute))
    src = [looped.table('int', 'CRBA_SIG', sig), looped.table('int', 'CRBA_AX', [2 if r else 5 for r in fr.revolute]),
           looped.table('double', 'CRBA_K0', [e for b in range(fr.nb) for e in looped.pose_out((fr.R[b], fr.t[b]))])]
    for i, rev in enumerate(kinds):
        src.append(looped.step(f'crba_xform{i}', lambda g, x, K, rev=rev: [
            looped.pose_out(joint_transform(g, *looped.pose_in(K), rev, x[0]))], (1, 12)))
        src.append(looped.step(f'crba_column{i}', lambda g, ic, rev=rev: [_F_flat(joint_wrench(rev, _ic(ic)))],
                               (10,)))
    src.append(looped.step('crba_composite', lambda g, a, X, p: [
        _ic_flat(composite(_ic(a), looped.pose_in(X), _ic(p)))], (10, 12, 10)))
    src.append(looped.step('crba_pair', lambda g, F, X: [
        _F_flat(la.wrench_to_parent((F[:3], F[3:]), *looped.pose_in(X)))], (6, 12)))
    xform = looped.switch('CRBA_SIG[b]', [f'crba_xform{i}' for i in range(len(kinds))],
                          '&x, CRBA_K0 + 12 * b, X + 12 * b')
    column = looped.switch('CRBA_SIG[b]', [f'crba_column{i}' for i in range(len(kinds))], 'IC + 10 * b, F')
    src.append(f'''
static void crba_pass(const double *q, const double *P, const double *E0, const double *AR, double *X, double *IC,
                      double *M)
{{
  double F[6];
  (void)E0;
  memcpy(IC, P, 10 * NB * sizeof(double));
  for (int b = 0; b < NB; b++) {{
    const double x = X_OF(q, E0, b);
    {xform}
  }}
  for (int b = NB - 1; b >= 0; b--)
    if (PAR[b] >= 0) crba_composite(IC + 10 * b, X + 12 * b, IC + 10 * PAR[b], IC + 10 * PAR[b]);
  memset(M, 0, NJ * NJ * sizeof(double));
  for (int b = 0; b < NB; b++) {{
    const int jb = JNT[b];
    if (jb < 0) continue;
    {column}
    M[jb * NJ + jb] = F[CRBA_AX[b]] + AR[jb];
    for (int j = b; PAR[j] >= 0; ) {{
      crba_pair(F, X + 12 * j, F);
      j = PAR[j];
      if (JNT[j] >= 0) M[JNT[j] * NJ + jb] = M[jb * NJ + JNT[j]] = F[CRBA_AX[j]];
    }}
  }}
}}
''')
    return ''.join(src)


MASS_MATRIX = Spec('mass_matrix', build_mass_matrix, ('inertia', 'offsets', 'armature'), 'mass_matrix',
                   result=lambda model: ((model.n, model.n), None), looped=looped_mass_matrix)
