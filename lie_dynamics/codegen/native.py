"""The native backend: the traced kernels rendered to C (crender.py), compiled once, cached on disk.

Switch: LIE_DYNAMICS_NATIVE = 'auto' (default: native when a C compiler works), '0' (never)
or 'require' (raise NativeUnavailable when it does not, naming the compiler and its first
error line). Under 'auto' a failing or missing compiler gives one warning per process and
the Python kernels, whose results are the same to rounding.

Compiler: $CC, else the compiler Python was built with, else `cc`; flags FLAGS for the call
path, KERNEL_FLAGS for the kernels (LOOPED_FLAGS for the looped ones; no -ffast-math,
-ffp-contract=off: the C kernels compute what the Python kernels compute, operation for
operation). A kernel's C text of several translation units (crender.py) is compiled on every
usable core and linked once. No -march:
the cache is per machine, but a home folder (and its cache) may move to another CPU; the
kernels across states (clanes.py) get their AVX2 form through `target_clones`, which the
loader picks by the CPU it runs on, with the baseline beside it.

Cache: disk_cache.py (named by a hash of everything that determines a file, checked before
loading, bounded); a cached kernel loads without being traced.
"""
import ctypes
import importlib.machinery
import importlib.util
import os
import shlex
import shutil
import subprocess
import sys
import sysconfig
import threading
import time
import warnings
from typing import NamedTuple

import numpy as np

from . import disk_cache
from .disk_cache import (CACHE_MAX_MB, MAGIC, STALE_BUILD_S, cache_dir, cache_max_bytes, evict,  # noqa: F401
                         generator_hash)
from .clanes import LANES
from .crender import UNIT   # _build compiles a text's units in parallel and links them once
from .thresholds import THRESHOLDS

HERE = os.path.dirname(os.path.abspath(__file__))
FLAGS = ('-O2', '-ffp-contract=off', '-fno-math-errno', '-fPIC', '-shared', '-pipe')   # -pipe: no temporary files
# The kernels: -O1 compiles in 30-40% less CPU time than -O2, and the straight-line parts run
# in 0.92-1.0x the time (no scheduling passes lengthening live ranges; every family on the arm
# and the Talos arm, interleaved rounds: python -m bench.compile --parts 500,500:-O2).
KERNEL_FLAGS = ('-O1',) + FLAGS[1:]
# The looped kernels (looped.py): the kernels' -O1. -O2 ran the mass matrix of a 200-body chain
# and the ABA of a 100-body one in 0.75-0.9x the time, but the ABA of a 16-body chain in 7-9x
# and the mass matrix of a 16-body chain in 3.4x (loaded machine, interleaved rounds, not
# explained yet): kept at -O1.
LOOPED_FLAGS = KERNEL_FLAGS
_LOCK = threading.Lock()
_STATE = {'module': None, 'error': None, 'warned': False, 'compiles': 0, 'seconds': 0.0, 'jobs': None}


class NativeUnavailable(RuntimeError):
    """LIE_DYNAMICS_NATIVE=require and the native backend cannot be built."""


def setting():
    """LIE_DYNAMICS_NATIVE: 'auto', '0' or 'require' (ValueError for anything else)."""
    v = os.environ.get('LIE_DYNAMICS_NATIVE', 'auto').strip().lower() or 'auto'
    if v in ('auto', '0', 'require'):
        return v
    raise ValueError(f"LIE_DYNAMICS_NATIVE must be 'auto', '0' or 'require', got {v!r}")


def wanted():
    """False when the native backend is switched off or known to be unavailable (under
    'require' the latter raises NativeUnavailable, every time)."""
    if setting() == '0':
        return False
    if _STATE['error'] is not None:
        _unavailable(_STATE['error'])
        return False
    return True


def compiler():
    """The C compiler command (a list): $CC, else Python's build compiler, else cc."""
    cc = os.environ.get('CC') or sysconfig.get_config_var('CC') or 'cc'
    return shlex.split(cc)


def compile_count():
    """C compilations this process has run (cache hits do not count)."""
    return _STATE['compiles']


def compile_seconds():
    """Wall-clock seconds this process has spent running the C compiler (and linker)."""
    return _STATE['seconds']


def _key(flags, *parts):
    return disk_cache.key(*parts, ' '.join(compiler()), ' '.join(flags))


def _first_error(text):
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    errs = [ln for ln in lines if 'error' in ln.lower()]
    return (errs or lines or ['(no output)'])[0]


def usable_cores():
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def set_jobs(n=None):
    """Run at most n compiler processes at once (None: one per usable core, the default). The
    dynamics node's build process leaves a core to the node's control path this way."""
    if n is not None and (not isinstance(n, int) or n < 1):
        raise ValueError(f'compiler jobs must be a positive integer or None, got {n!r}')
    _STATE['jobs'] = n


def _jobs():
    return min(usable_cores(), _STATE['jobs'] or usable_cores())


def _run(cmds):
    """Run compiler commands in parallel; NativeUnavailable naming the first error."""
    procs = []
    try:
        for c in cmds:
            procs.append(subprocess.Popen(c, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
        outs = [p.communicate(timeout=600)[0] for p in procs]
    except (OSError, subprocess.SubprocessError) as e:   # no compiler, or one running too long
        for p in procs:
            p.kill()
            p.communicate()
        raise NativeUnavailable(f'C compiler {" ".join(compiler())!r} failed: {e}') from None
    for p, out in zip(procs, outs):
        if p.returncode != 0:
            raise NativeUnavailable(f'C compiler {" ".join(compiler())!r} failed: {_first_error(out)}')


def _build(source, lib, work, flags):
    """Compile C text `source` into the shared library `lib`. A text of several translation
    units (UNIT between them) is compiled as up to one object per usable core (set_jobs), in
    parallel, consecutive units together in pieces of about equal length, and linked once."""
    units = source.split(UNIT)
    jobs = min(len(units), _jobs())
    pieces, acc, done, total = [], [], 0, sum(map(len, units))
    for u in units:   # cut where the running length passes the next k/jobs of the total
        acc.append(u)
        done += len(u)
        if done >= total * (len(pieces) + 1) / jobs:
            pieces.append(acc)
            acc = []
    if acc:
        pieces.append(acc)
    srcs = []
    for k, p in enumerate(pieces):
        srcs.append(os.path.join(work, f'k{k}.c'))
        with open(srcs[-1], 'w', encoding='utf-8') as fh:
            fh.write(''.join(p))
    if len(srcs) == 1:   # one process, no separate link
        _run([compiler() + flags + ['-o', lib, srcs[0]]])
    else:
        objs = [s[:-2] + '.o' for s in srcs]
        _run([compiler() + flags + ['-c', '-o', o, s] for s, o in zip(srcs, objs)])
        _run([compiler() + flags + ['-o', lib, *objs]])
    if not os.path.exists(lib):
        raise NativeUnavailable(f'C compiler {" ".join(compiler())!r} failed: no {os.path.basename(lib)} written')


def _compile(source, key, suffix, flags):
    """(path of the verified library for key, temporary folder to remove after loading or
    None), compiling `source` (C text) on a miss."""
    path = disk_cache.path_of(key, suffix)
    if disk_cache.verified(path, key):
        return path, None
    work, tmpdir = disk_cache.work_folder()
    try:
        lib = os.path.join(work, 'k' + suffix)
        t0 = time.perf_counter()
        try:
            _build(source, lib, work, list(flags))
        finally:
            _STATE['seconds'] += time.perf_counter() - t0
        _STATE['compiles'] += 1
        return disk_cache.store(lib, key, suffix, tmpdir is not None), tmpdir
    finally:
        if tmpdir is None:
            shutil.rmtree(work, ignore_errors=True)


def _call_module():
    """The extension module of the call path (native_call.c), built or loaded once."""
    texts = {}
    parts = ('native_method.c', 'native_command.c')   # included by native_call.c
    for name in ('native_call.c',) + parts:
        with open(os.path.join(HERE, name), encoding='utf-8') as fh:
            texts[name] = fh.read()
    source = texts['native_call.c']
    for name in parts:
        source = source.replace(f'#include "{name}"', texts[name])
    incs = [sysconfig.get_paths()['include'], np.get_include()]
    flags = FLAGS + ('-pthread',) + tuple(f'-I{i}' for i in incs)   # set_threads: POSIX threads
    key = _key(flags, source, sys.version, np.__version__)
    suffix = importlib.machinery.EXTENSION_SUFFIXES[0]
    path, tmp = _compile(source, key, suffix, flags)
    try:
        spec = importlib.util.spec_from_file_location('lie_dynamics_native', path)
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    finally:
        if tmp:
            shutil.rmtree(tmp, ignore_errors=True)
    return mod


def module():
    """The call module, or None when the native backend is off or cannot be built (one
    warning per process under 'auto'; NativeUnavailable under 'require')."""
    mode = setting()
    if mode == '0':
        return None
    m = _STATE['module']
    if m is not None:
        return m
    with _LOCK:
        if _STATE['module'] is None and _STATE['error'] is None:
            try:
                _STATE['module'] = _call_module()
            except NativeUnavailable as e:
                _STATE['error'] = str(e)
    if _STATE['error'] is not None:
        _unavailable(_STATE['error'])
        return None
    return _STATE['module']


def invalidate():
    """Every native-first method (dispatch.native_first) resolves its kernel again: the runtime
    forgot kernels or changed a model's switch (cache.clear, forget, use_native)."""
    if _STATE['module'] is not None:
        _STATE['module'].invalidate()


def _unavailable(msg):
    if setting() == 'require':
        raise NativeUnavailable(f'LIE_DYNAMICS_NATIVE=require, but {msg}')
    if not _STATE['warned']:
        _STATE['warned'] = True
        warnings.warn(f'lie_dynamics: native kernels unavailable ({msg}); using the Python kernels',
                      RuntimeWarning, stacklevel=3)


class Library:
    """A compiled kernel: its address and signature (widths of the per-state lists, lengths
    of the parameter lists, number of outputs), read from the library itself."""

    def __init__(self, path):
        self.lib = ctypes.CDLL(path)
        meta = (ctypes.c_long * 64).in_dll(self.lib, 'lie_meta')
        n_in, n_par, self.n_out = meta[0], meta[1], meta[2]
        self.widths = tuple(meta[3:3 + n_in])
        self.par_lengths = tuple(meta[3 + n_in:3 + n_in + n_par])
        self.address = ctypes.cast(self.lib.lie_kernel, ctypes.c_void_p).value
        try:   # the form on clanes.LANES states at once, when the kernel is small enough to have one
            self.lanes_address = ctypes.cast(self.lib.lie_kernel_lanes, ctypes.c_void_p).value
            n_sc = ctypes.c_long.in_dll(self.lib, 'lie_lanes_sincos').value
            table = (ctypes.c_long * (1 + 2 * n_sc)).in_dll(self.lib, 'lie_lanes_sincos')
            self.lanes_sincos = tuple(table[1:])   # (list, position) of each input it takes sin and cos of
        except AttributeError:
            self.lanes_address, self.lanes_sincos = 0, ()


class Rendered(NamedTuple):
    """A kernel rendered to C for `library`: the C text and its signature."""
    source: str
    widths: tuple        # values per per-state argument list
    par_lengths: tuple   # values per parameter list
    n_out: int


def library(structure, name, render, flags=None):
    """The Library of kernel `name` for a model structure (its fingerprint): from the cache,
    else compiled with `flags` (None: KERNEL_FLAGS, read at the call) from render() -> Rendered,
    or None (no such kernel). None when the backend is off or unavailable (module())."""
    if module() is None:
        return None
    flags = KERNEL_FLAGS if flags is None else flags
    key = _key(flags, generator_hash(), structure, name, THRESHOLDS['native_part'])
    path = disk_cache.path_of(key, '.so')
    for attempt in (0, 1):
        tmp = None
        if not disk_cache.verified(path, key):
            rendered = render()
            if rendered is None:
                return None
            meta = [len(rendered.widths), len(rendered.par_lengths), rendered.n_out, *rendered.widths,
                    *rendered.par_lengths]
            if len(meta) > 64:
                return None
            meta = ', '.join(str(int(v)) for v in meta)
            source = f'{rendered.source}const long lie_meta[64] = {{{meta}}};\n'
            try:
                path, tmp = _compile(source, key, '.so', flags)
            except NativeUnavailable as e:
                _unavailable(str(e))
                return None
        try:
            return Library(path)
        except OSError:   # evicted by another process between the check and the load: once more
            if attempt:
                raise
        finally:
            if tmp:
                shutil.rmtree(tmp, ignore_errors=True)


def bind(lib, params, result, gil_rows):
    """A callable running lib's kernel with these parameter lists (sequences of floats) and its
    outputs read as `result` (spec.Result: shape, size, rtol; pivots tested when rtol is not
    None); batches of gil_rows states or more run with the GIL released.
    call(*per_state_arrays[, out]) -> result, or None when it declines (native_call.c)."""
    arrays = tuple(np.ascontiguousarray(p, dtype=float).reshape(-1) if len(p) else np.zeros(1) for p in params)
    check = result.rtol is not None
    # native_call.c's bind(address, lanes address, lanes, sincos, widths, params, n_out, n_res, out_dims, check,
    # rtol, gil_rows, keep)
    return module().bind(lib.address, lib.lanes_address, LANES, lib.lanes_sincos, lib.widths, arrays, lib.n_out,
                         result.size, tuple(result.shape), int(check), result.rtol if check else 0.0, gil_rows,
                         (lib, arrays))


def set_threads(n=None, min_rows=None):
    """Threads for the native batches (process-wide): a batch of at least `min_rows` states per
    thread (default THRESHOLDS['native_thread_rows']) runs on up to n threads at once in C, the
    GIL released, which take its rows a part at a time (large parts first, small ones at the
    end; a thread that starts late takes fewer); results are identical to one thread (each
    state's outputs depend on that state alone). The helper threads are started by the first
    threaded batch and kept: after a batch each spins up to 200 us, then sleeps until the next
    (native_call.c run_pooled). n None: LIE_DYNAMICS_THREADS, else 1. Returns the previous
    count; None when the backend is off."""
    if n is None:
        env = os.environ.get('LIE_DYNAMICS_THREADS', '').strip()
        n = int(env) if env.isdigit() else 1
    if not isinstance(n, int) or isinstance(n, bool) or not 1 <= n <= 64:
        raise ValueError(f'threads must be an integer from 1 to 64, got {n!r}')
    m = module()
    if m is None:
        return None
    return m.set_threads(n, THRESHOLDS['native_thread_rows'] if min_rows is None else int(min_rows))
