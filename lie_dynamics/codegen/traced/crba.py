"""The composite rigid body algorithm, traced (the recursive form of eq 39; algorithms/crba.py)."""
from .. import algebra as la
from ..kernel import Trace
from ..runtime import Spec
from ..tracer import Graph


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
            m, h, Io = la.inertia_to_parent(ic[b], *X[b])
            mp, hp, Ip = ic[p]
            ic[p] = (mp + m, la.vadd(hp, h), la.vadd(Ip, Io))

    def s_dot(b, F):
        return F[0][2] if fr.revolute[b] else F[1][2]

    Mx = [[0.0] * nb for _ in range(nb)]
    for b in range(nb):
        m, h, Io = ic[b]
        if fr.revolute[b]:
            F = ((Io[2], Io[4], Io[5]), (-h[1], h[0], 0.0))
        else:
            F = ((h[1], -h[0], 0.0), (0.0, 0.0, m))
        Mx[b][b] = s_dot(b, F)
        j = b
        while fr.parent[j] >= 0:
            F = la.wrench_to_parent(F, *X[j])
            j = fr.parent[j]
            Mx[j][b] = Mx[b][j] = s_dot(j, F)
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


MASS_MATRIX = Spec('mass_matrix', build_mass_matrix, ('inertia', 'offsets', 'armature'), 'mass_matrix',
                   result=lambda model: ((model.n, model.n), None))
