"""THRESHOLDS: every size threshold of the generated kernels, with the measurement that chose it;
PD_RTOL: the positive-definiteness tolerance every forward-dynamics path shares.

runtime.py routes by it (runtime.route) and re-exports it: `runtime.THRESHOLDS` is this dict.
"""
from typing import NamedTuple

# A pivot d_j^2 below PD_RTOL times its diagonal entry M_jj means near-dependence: a joint
# that moves no mass of its own (massless body or chain). Blind to the scale of the masses.
# Here, below the algorithms, because the generated kernels' results are checked with it too
# (their Spec.result gives it to runtime.accepts); algorithms/cholesky.py re-exports it.
PD_RTOL = 1e-12


class Limits(NamedTuple):
    """When a kernel runs, by model size (`size`: bodies, or (body, ancestor-or-self) pairs,
    the sum of the body depths) and by the number of states N of a call."""
    compile_max: int          # no Python kernel above this size (compile time grows with the source)
    float_max: int            # above: one state and small batches take the vectorised reference
    loop_below: int           # N below this: the float kernel, state by state
    rows_from: int            # N from this: the kernel on numpy rows; in between: vectorised
    size: str = 'bodies'
    large: int = None         # above this size, rows from rows_from_large states
    rows_from_large: int = None
    native_max: int = None    # no native kernel above this size (None: compile_max)
    looped_from: int = None   # from this size the looped native form (codegen/looped.py) replaces the
    #                           straight-line one, at any size, and above the native caps (None: no looped form)
    looped_size: str = None   # how looped_from counts: 'bodies' or 'pairs' (None: as `size`)


# Every size threshold of the algorithms, with the measurement that chose it (timings on the
# 7-DoF arm and random chains and trees, this 2-core machine, numpy 2.4, Python 3.11).
# Backend dimension: where a native kernel exists (native.py; size within compile_max and
# native_nodes) it runs at every N, one state and batches alike, and the Limits below route
# only the Python backend. Measured per state, µs (arm / 30-body chain, inverse dynamics;
# busy machine, minima of 3-5 repeats): N = 1: native 0.35 / 9, Python float kernel 32 / 730;
# N = 100: native 0.18 / 2.4, rows 3.1 / 82; N = 10,000: native 0.2-0.4 / 1.9, rows 0.7-1.6 / 4.
# Mass matrix on the arm: native 0.16-0.4 against rows 0.4-1.0 from N = 1,000.
THRESHOLDS = {
    # RNEA: compile time grows with the source, and above 256 bodies the vectorised form is
    # as fast for batches. The float kernel (~15 ns per flop) is slower than the vectorised
    # reference for one state above ~48 bodies. A Python loop of the float kernel beats the
    # rows kernel below ~30 states on the arm (each row operation costs ~0.5 us whatever its
    # length).
    'inverse_dynamics': Limits(256, 48, 32, 32),
    # Gravity (subtree masses, a few operations per body): the float kernel wins for one
    # state at every size up to the compile cap; loop/rows crossover as inverse dynamics.
    'gravity': Limits(256, 256, 32, 32),
    # CRBA: the O(n^2) source takes long to compile above 24 bodies; the float loop beats the
    # vectorised form up to ~40 states on the arm, where the in-place rows take over.
    # native_max (every native_max: `python -m bench.native_sizes`, machine load 7-18; and
    # native_nodes): on Baxter, PR2, Talos reduced, random trees of 32-64 bodies and a 32-body
    # chain the native M (2,500-18,000 nodes) compiles in 0.3-3.1 s of compiler CPU and runs
    # 0.1-1.2x Pinocchio's crba; a 64-body chain has 66,000 nodes.
    # looped_from, counted in (body, ancestor) pairs, the straight-line M's size (`python -m bench.looped`, load
    # 3-9, one state, looped / straight-line at -O1, medians of per-round ratios): chains of 16-32 bodies (136-528
    # pairs) 1.6-2.1, 48 (1,176) 1.3, 64 (2,080) 0.7; binary trees of 16-32 bodies (~50-130 pairs) 1-5. First use
    # 0.1-0.3 s looped, against 0.7-3 s straight-line up to 32 bodies, 6-16 s at 48 and 21 s at 64 (loaded). Hence
    # looped from 1,000 pairs (a 45-body chain), and above native_max (trees of 100-200 bodies) whatever the pairs.
    # The looped M runs 0.2-0.85x Pinocchio's crba on chains of 100-200 bodies.
    'mass_matrix': Limits(24, 24, 40, 40, native_max=64, looped_from=1000, looped_size='pairs'),
    # Cholesky forward dynamics (CRBA + RNEA bias + factorisation, O(n^2) source, the CRBA's
    # cap); the float loop beats the rows up to ~48 states on the arm, and the kernel beats
    # the composed numpy path at every batch size.
    # Native: 6,000-51,000 nodes on the same robots, 0.5-4 s of compiler CPU, 0.05-1.15x
    # Pinocchio's aba; a 64-body chain (178,000 nodes) is above native_nodes.
    'forward_dynamics': Limits(24, 24, 48, 48, native_max=64),
    # ABA (O(n) source): build time grows ~12 ms per body (0.3 s at 24, 1.2 s at 120) while
    # the kernel stays ~10x faster than the vectorised form; loop/rows crossovers 28-48
    # states for 2-24 bodies, the vectorised form never clearly faster in between.
    # looped_from (`python -m bench.looped`, as the mass matrix's): the looped ABA runs 0.9-1.1x
    # the straight-line one on chains of 8-16 bodies and trees of 32 (single rounds swing 0.6-4x
    # at 32-64 under that load), 0.3x Pinocchio's aba from 24 bodies (0.3x on chains of 100 and
    # 200); first use 0.2-0.4 s against 0.5-5 s. Forward dynamics (method='cholesky') takes it
    # from here too (algorithms/aba.py): 0.44-0.8x the straight-line Cholesky kernel on chains of
    # 8-32 and a 32-body tree, and O(n) where that kernel's O(n^3) source stops at native_nodes.
    'aba': Limits(128, 128, 32, 32, looped_from=24),
    # Derivatives of inverse dynamics (and C = 1/2 dtau/dqd): above 16 bodies one state is
    # faster through the vectorised form; crossovers 4 (loop) and 128 (rows) on 7-20 bodies.
    # Native (and the Coriolis kernel): 8,000-59,000 nodes on the same robots, 0.8-9.4 s of
    # compiler CPU (the 64-body tree's 59,000 nodes), 0.1-0.4x Pinocchio's computeRNEADerivatives
    # (computeCoriolisMatrix 0.1-0.2x, 1.4x in a load spike); a 64-body chain (160,000 nodes) is
    # above native_nodes.
    # looped_from (`python -m bench.looped --families inverse_dynamics_derivatives,coriolis`, load
    # 1.3-2.9, one state, medians of per-round ratios; C takes the same kernel's route): looped /
    # straight-line 1.03-1.3 on chains of 6-8 bodies, 0.9-1.0 from 10-16 bodies (chains, trees,
    # Talos reduced), 0.6-1.7 at 24-64 (noisy under that load); first use 0.15-0.5 s looped against
    # 0.4-2.3 s up to 16 bodies, 3-9 s at 24-32 and 6-20 s at 48-64. Hence looped from 12 bodies,
    # and at any size above the caps: 0.35-0.6x Pinocchio's computeRNEADerivatives (C: 0.35-0.6x
    # computeCoriolisMatrix) on 12-64 bodies, 0.8 / 1.0x on chains of 100 / 200 bodies and
    # 0.6 / 0.9x on trees of 100 / 200 (C: 0.75 / 0.8x and 0.6 / 0.7x).
    'inverse_dynamics_derivatives': Limits(16, 16, 4, 128, native_max=64, looped_from=12),
    # Derivatives of forward dynamics (the derivative kernel's cap); crossovers on the arm
    # ~8 (loop) and ~80 (rows).
    # Native: O(n^3) source (M^-1 times the RNEA derivatives): 25,000-85,000 nodes on Baxter, PR2,
    # Talos reduced and a 32-body tree (2.4-8 s of compiler CPU, the largest family), 0.15-0.4x
    # Pinocchio's computeABADerivatives; a 32-body chain has 262,000 nodes (traced in ~5 s, then
    # above native_nodes), a 64-body tree 456,000: 32 bodies bounds the wasted trace.
    # looped_from (`python -m bench.looped --families forward_dynamics_derivatives`, load 3-6, one
    # state, medians of per-round ratios): the looped kernel (traced/derivatives.py, the L^T D L
    # solves in C) runs 1.1-1.8x the straight-line one on chains of 6-16 bodies (0.75-3.3 on trees
    # of 16-24 in single runs at load 5-6), 0.33x on a 32-body tree, 1.07x on Talos reduced; first
    # use 0.4-1.6 s against 1.2-9 s up to 16 bodies and 7-29 s at 24-32 (chains from 24 bodies are
    # above native_nodes). Hence looped from 17 bodies, at any size above the caps: 0.35-0.5x
    # computeABADerivatives on trees of 24-200 bodies and Talos reduced, 1.2-2.1x on chains of
    # 24-64, 1.6-3.2x on chains of 100-200 (its M^-1 times dtau is O(n^3) there, a dense GEMM in
    # Pinocchio).
    'forward_dynamics_derivatives': Limits(16, 16, 8, 80, native_max=32, looped_from=17),
    # Regressor, sized in pairs: 300 pairs (a 24-body chain) compile in ~0.5-0.8 s. The
    # float kernel (~22 ns per operation, 60-95 per pair) beats the vectorised form for one
    # state up to ~130-160 pairs. Loop below ~7 states on the arm (3-5 on 10-12-body robots
    # with general axes); rows from ~80 states on the arm and 20-100 up to 64 pairs, 40-280
    # for 100-300 pairs (later for chains, earlier for branched trees).
    # Native: 5,000-51,000 nodes up to 528 pairs (a 32-body chain), 0.9-8.2 s of compiler CPU,
    # 0.1-0.6x Pinocchio's computeJointTorqueRegressor; a 64-body chain (2,080 pairs) has 200,000.
    # looped_from (`python -m bench.looped --families regressor`, load 2.4-4, one state, medians of
    # 7-21 interleaved rounds): looped / straight-line 1.13-1.17 on the arm (28 pairs), 0.9-1.07 on
    # chains of 8-16 bodies (36-136 pairs), binary trees of 16-100 bodies (50-486 pairs) and Talos
    # reduced (156 pairs, 1.03 once its pair steps fold the constant entries of the body's pose;
    # 2.2 before), 0.6-0.7 on chains of 24-32 (300-528 pairs); first use 0.1-0.7 s against 1-10 s.
    # Hence looped from 64 pairs (an 11-body chain): the arms keep their straight-line kernel, and
    # above native_max whatever the pairs. The looped regressor runs 0.15-0.3x Pinocchio on chains
    # of 48-200 bodies, 0.6-0.96x on binary trees of 100-200 (two runs, load 3-6; docs/benchmarks.md).
    # Mimic joints: no looped form (every such robot of example-robot-data is within native_max).
    'regressor': Limits(300, 128, 6, 80, size='pairs', large=64, rows_from_large=192, native_max=600,
                        looped_from=64),
    # Frame Jacobians and J̇q̇ (one kernel per kind, frame and body, O(depth) source): on random
    # chains (tip link) the float kernel beats the vectorised form for one state up to ~96 bodies,
    # 1.3-1.6x at 64 where a build takes 0.1-0.2 s (0.3 s at 128); on the arm the loop/rows
    # crossover is 24-40 states, the vectorised form never faster in between.
    # native_max: no looped form, the O(depth) source stays small (the tip of a 200-body chain:
    # 13,000 nodes for J, 22,000 for J̇q̇). `python -m bench.looped --families jacobian,jacobian_dot`
    # (deepest link, cap lifted, load 2.8-3): first use 0.6-2.4 s on chains of 32-200 bodies, 0.1-0.65 s
    # on binary trees of 64-200; J 0.54-0.82x pin.computeFrameJacobian on those chains, J̇q̇ 0.3-0.5x
    # its classical acceleration, 0.06-0.2x on the trees (J 1.7-2x there then: Pinocchio's ~1-2 us
    # against the Python call path's ~1 us over the kernel; since the methods call the kernel from
    # C, 0.72x and 0.85x on the trees of 32 and 64 bodies, load 3.9). Above 256 bodies, native_nodes still
    # bounds a deep link's kernel (~110 nodes per body of depth for J̇q̇).
    'jacobian': Limits(64, 64, 32, 32, native_max=256),
    # Batch runner: states per chunk, large enough that each ufunc's ~0.5 us fixed cost is
    # small next to its per-element work, small enough that the rows stay in cache (at most
    # ~8 MB of registers and inputs per chunk).
    'rows_chunk': 4096,
    'rows_bytes': 8 << 20,
    # Regressor rows: states per call of the batch runner, bounding its (outputs, states)
    # result (up to 10 nb^2 outputs).
    'regressor_rows_chunk': 8192,
    # Vectorised references: floats of work arrays per chunk of states (2^21: 16 MB).
    'vectorized_budget': 1 << 21,
    # Native kernels are cut into functions of at most this many graph nodes (crender.py): gcc's
    # register allocation grows faster than a straight-line body. The arm's forward-dynamics
    # derivatives (7,500 nodes), compiler CPU time: one function 1.6-1.8 s at -O2 (as before
    # the cut), 1.3-1.5 s at -O1; parts of 250, 500 or 1,000 at -O1 (native.KERNEL_FLAGS)
    # 0.6-0.7 s, spread over both cores. Parts of 250-500 call 0.85-1.0x the time of one
    # function on every family of the arm and the Talos arm (1,000: up to 1.16x). None: one
    # function. `python -m bench.compile --parts 500,250,1000,none --robots arm7,talos_arm`.
    'native_part': 500,
    # Above this many graph nodes a kernel stays Python. Cut into parts, compile time grows
    # linearly: ~0.08-0.1 s of compiler CPU per 1,000 nodes (derivative kernels of random chains
    # of 8-16 joints, 6,400-49,000 nodes, `python -m bench.compile --chains 8,12,16`; every family
    # of PR2, Baxter, Talos reduced and random trees and chains of 32-64 bodies, 460-85,000
    # nodes, `python -m bench.native_sizes`), about half of it in wall time on 2 cores; the
    # native kernel beats the Python kernels at every batch size. 100,000 lets every family of
    # those robots go native (the largest, forward-dynamics derivatives of a 32-body tree,
    # 85,000 nodes, ~8 s of CPU, ~4 s on 2 quiet cores, once: the disk cache keeps it) but
    # the O(n^2) and O(n^3) families of long chains (64 bodies: 160,000-1,700,000 nodes): there the
    # looped form runs where a family has one (looped_from: M, ABA and forward dynamics, the
    # regressor, both derivative families and C; docs/architecture.md, "Looped native kernels"),
    # else the vectorised reference.
    'native_nodes': 100000,
    # Native batches release the GIL from this many states (below, the release costs more
    # than other threads gain).
    'native_gil_rows': 64,
    # Kernels of clanes.FAMILIES of at most this many graph nodes also get the form on
    # clanes.LANES states at once (clanes.py), which batches run: inverse dynamics of the 6-7-joint
    # arms has ~1,000 nodes.
    'native_lanes_nodes': 2500,
    # native.set_threads: a batch is cut among threads only with at least this many states per
    # thread (starting a thread costs ~10-30 us, 30-100 states of an arm's inverse dynamics).
    'native_thread_rows': 1024,
    # Compiled kernels kept for structures no live model uses (about 10 per structure).
    'compiled_cache': 256,
}
