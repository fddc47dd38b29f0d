"""The batch runner: a kernel's float function state by state (`run_loop`) or its rows form on
a chunked batch (`run_rows`), with the runner's own state per kernel (block layout, pool)."""
import contextlib
import threading
import weakref

import numpy as np

from .thresholds import THRESHOLDS

_NO_ERRSTATE = contextlib.nullcontext()
_LOOPS = {}


def run_loop(fn, arrays, params):
    """The float kernel state by state: arrays (N, k) (the per-state arguments, first in the
    kernel's order), params the parameter lists that follow them. A list of output tuples."""
    key = (len(arrays), len(params))
    loop = _LOOPS.get(key)
    if loop is None:   # the arguments spelt out: ~0.2 us per state less than fn(*r, *params)
        a = ', '.join(f'a{i}' for i in range(key[0]))
        p = ''.join(f', p{i}' for i in range(key[1]))
        rows = 'lists[0]' if key[0] == 1 else 'zip(*lists, strict=True)'
        src = (f'def loop(fn, lists, params):\n    ({p[2:]}{"," if p else ""}) = params\n'
               f'    return [fn({a}{p}) for {a} in {rows}]\n')
        ns = {}
        exec(compile(src, '<lie_dynamics run_loop>', 'exec'), ns)
        loop = _LOOPS[key] = ns['loop']
    return loop(fn, [x.tolist() for x in arrays], params)


class _Rows:
    """The batch runner's state for one kernel: its register block's height, the states of one
    chunk, and the pool of blocks kept between calls (pooled kernels)."""
    __slots__ = ('height', 'size', 'pool')

    def __init__(self, k):
        self.height = k.nreg + 1 + sum(k.widths[:k.n_state])
        self.size = int(min(THRESHOLDS['rows_chunk'], max(256, THRESHOLDS['rows_bytes'] // (8 * self.height))))
        self.pool = []


_RUNNERS = weakref.WeakKeyDictionary()   # Kernel -> _Rows: dropped with the kernel (the LRU evicts it)
_RUNNERS_LOCK = threading.Lock()


def _runner(k):
    r = _RUNNERS.get(k)
    if r is None:
        with _RUNNERS_LOCK:
            r = _RUNNERS.get(k)
            if r is None:
                r = _RUNNERS[k] = _Rows(k)
    return r


def run_rows(k, args, chunk=None, out=None, quiet=True, pooled=False):
    """Run Kernel k's rows form on a batch: args in the kernel's order, (N, width) arrays for
    its per-state lists (Kernel.roles), then the parameter sequences. Returns (N, k.n_out): `out` when given
    (written column by column), else the transpose of a state-last array. quiet: no
    floating-point warnings (for callers that check the outputs).

    States go in chunks (THRESHOLDS rows_chunk / rows_bytes), copied transposed into input
    rows of one register block; every operation writes into the block (render.emit_rows), so
    a chunk allocates nothing but its outputs. When `pooled`, blocks are reused across calls
    from a pool per kernel (concurrent callers never share one; later calls touch no fresh
    pages): worth it for the cheap per-call kernels (inverse dynamics, gravity). The others
    allocate per call: a block held in a pool is never freed, so glibc never raises its mmap
    threshold above it, and every large temporary of such a call (e.g. the regressor's
    output) stays a fresh mmap with its page faults.
    """
    rows_fn = k.rows()
    runner = _runner(k)
    height = runner.height
    size = chunk or runner.size
    regs = k.nreg + 1
    idx = range(k.n_state)
    n_out = k.n_out
    N = args[0].shape[0]
    pool = runner.pool
    buf = pool.pop() if pooled and pool else None
    if buf is None or buf.size < height * min(size, N):
        buf = np.empty(height * (size if pooled else min(size, N)))
    res = np.empty((n_out, N)) if out is None else None
    call = list(args)
    errs = np.errstate(all='ignore') if quiet else _NO_ERRSTATE
    try:
        with errs:
            for start in range(0, N, size):
                stop = min(N, start + size)
                view = buf[:height * (stop - start)].reshape(height, stop - start)   # adjacent rows
                r = regs
                for i in idx:
                    w = k.widths[i]
                    view[r:r + w] = args[i][start:stop].T
                    call[i] = view[r:r + w]
                    r += w
                vals = rows_fn(*call, list(view[:regs]))
                if out is None:
                    for j, v in enumerate(vals):
                        res[j, start:stop] = v
                else:
                    for j, v in enumerate(vals):
                        out[start:stop, j] = v
    finally:
        if pooled:
            pool.append(buf)
    return res.T if out is None else out
