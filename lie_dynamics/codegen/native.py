"""The native backend: the traced kernels rendered to C (crender.py), compiled once, cached on disk.

Switch: LIE_DYNAMICS_NATIVE = 'auto' (default: native when a C compiler works), '0' (never)
or 'require' (raise NativeUnavailable when it does not, naming the compiler and its first
error line). Under 'auto' a failing or missing compiler gives one warning per process and
the Python kernels, whose results are the same to rounding.

Compiler: $CC, else the compiler Python was built with, else `cc`; flags FLAGS for the call
path, KERNEL_FLAGS for the kernels (no -ffast-math, -ffp-contract=off: the C kernels compute
what the Python kernels compute, operation for operation). A kernel's C text of several
translation units (crender.py) is compiled on every usable core and linked once.

Cache: $LIE_DYNAMICS_CACHE_DIR, else $XDG_CACHE_HOME/lie_dynamics, else ~/.cache/lie_dynamics;
a file is named by a hash of everything that determines it (the generator's own source, the
model structure, kernel name and THRESHOLDS['native_part'], or the call path's C source,
with the compiler, its flags and the Python/numpy versions), so a cached kernel
loads without being traced. Every file ends with a trailer (MAGIC, its key, the SHA-256 of
the bytes before it), checked before loading: a truncated or foreign file is rebuilt, never
loaded. Files are written to a temporary name and renamed into place (two processes
compiling the same kernel both succeed); an unwritable cache folder means compiling in a
temporary folder, removed after loading. The folder is bounded: $LIE_DYNAMICS_CACHE_MAX_MB
(default CACHE_MAX_MB); a file's time is its last use, and after each compile the least
recently used files go until the folder holds 3/4 of the bound (`evict`).
"""
import ctypes
import functools
import glob
import hashlib
import importlib.machinery
import importlib.util
import os
import shlex
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import threading
import time
import warnings

import numpy as np

from .thresholds import THRESHOLDS

HERE = os.path.dirname(os.path.abspath(__file__))
FLAGS = ('-O2', '-ffp-contract=off', '-fno-math-errno', '-fPIC', '-shared', '-pipe')   # -pipe: no temporary files
# The kernels: -O1 compiles in 30-40% less CPU time than -O2, and the straight-line parts run
# in 0.92-1.0x the time (no scheduling passes lengthening live ranges; every family on the arm
# and the Talos arm, interleaved rounds: python -m bench.compile --parts 500,500:-O2).
KERNEL_FLAGS = ('-O1',) + FLAGS[1:]
MAGIC = b'\nlie_dynamics native '
_TRAILER = len(MAGIC) + 64 + 64
# Between translation units in one C text (crender.emit_c; the whole text is valid C as well):
# _build compiles the units in parallel and links them once.
UNIT = '/* lie_dynamics: translation unit */\n'
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
    if os.environ.get('LIE_DYNAMICS_NATIVE', 'auto').strip() == '0':
        return False
    if _STATE['error'] is not None:
        _unavailable(_STATE['error'])
        return False
    return True


def compiler():
    """The C compiler command (a list): $CC, else Python's build compiler, else cc."""
    cc = os.environ.get('CC') or sysconfig.get_config_var('CC') or 'cc'
    return shlex.split(cc)


def cache_dir():
    d = os.environ.get('LIE_DYNAMICS_CACHE_DIR')
    if d:
        return d
    base = os.environ.get('XDG_CACHE_HOME') or os.path.join(os.path.expanduser('~'), '.cache')
    return os.path.join(base, 'lie_dynamics')


def compile_count():
    """C compilations this process has run (cache hits do not count)."""
    return _STATE['compiles']


def compile_seconds():
    """Wall-clock seconds this process has spent running the C compiler (and linker)."""
    return _STATE['seconds']


@functools.lru_cache(maxsize=1)
def generator_hash():
    """Hash of the source that determines the C kernels (the tracer, renderers, traced forms)."""
    h = hashlib.sha256()
    for path in sorted(glob.glob(os.path.join(HERE, '*.py')) + glob.glob(os.path.join(HERE, 'traced', '*.py'))):
        with open(path, 'rb') as fh:
            h.update(os.path.basename(path).encode() + fh.read())
    h.update(f'{sys.version_info[:2]} {np.__version__}'.encode())
    return h.hexdigest()


def _key(flags, *parts):
    h = hashlib.sha256()
    for p in parts + (' '.join(compiler()), ' '.join(flags)):
        h.update(str(p).encode() + b'\0')
    return h.hexdigest()


def _verified(path, key):
    """True when path ends with the trailer of key and the SHA-256 of the bytes before it; its
    time is then set to now (its last use, which `evict` reads)."""
    try:
        with open(path, 'rb') as fh:
            data = fh.read()
    except OSError:
        return False
    if len(data) <= _TRAILER or not data.endswith(MAGIC + key.encode() + hashlib.sha256(data[:-_TRAILER]).hexdigest()
                                                  .encode()):
        return False
    try:
        os.utime(path)
    except OSError:   # a read-only cache is still used
        pass
    return True


CACHE_MAX_MB = 512.0   # about ten times what a busy development machine collects
STALE_BUILD_S = 3600.0  # a build folder this old belongs to a process that died while compiling


def cache_max_bytes():
    """The bound of the cache folder: $LIE_DYNAMICS_CACHE_MAX_MB (a positive finite number), else CACHE_MAX_MB."""
    text = os.environ.get('LIE_DYNAMICS_CACHE_MAX_MB', '').strip()
    try:
        mb = float(text) if text else CACHE_MAX_MB
    except ValueError:
        mb = CACHE_MAX_MB
    return int((mb if 0 < mb < float('inf') else CACHE_MAX_MB) * 2 ** 20)   # nan, inf, <= 0: the default


def evict(folder, max_bytes, keep=(), now=None):
    """Bound the cache folder: when its libraries hold more than max_bytes, remove the least
    recently used (oldest time) until they hold at most 3/4 of it, never one in `keep`; build
    folders older than STALE_BUILD_S go too. Returns the removed paths. Files another process
    has loaded stay mapped there (removing only unlinks them)."""
    now = time.time() if now is None else now
    removed, files = [], []
    try:
        entries = list(os.scandir(folder))   # types from the directory itself: one stat per file, not two
    except OSError:
        return removed
    for e in entries:
        try:
            if e.name.startswith('build-') and now - e.stat().st_mtime > STALE_BUILD_S:
                shutil.rmtree(e.path, ignore_errors=True)
                removed.append(e.path)
            elif e.name.endswith('.so') and e.is_file():
                st = e.stat()
                files.append((st.st_mtime, st.st_size, e.path))
        except OSError:   # removed meanwhile
            continue
    total = sum(size for _, size, _ in files)
    if total <= max_bytes:
        return removed
    keep = {os.path.abspath(k) for k in keep}
    for _, size, path in sorted(files):
        if total <= 0.75 * max_bytes:
            break
        if os.path.abspath(path) in keep:
            continue
        try:
            os.remove(path)
        except OSError:
            continue
        total -= size
        removed.append(path)
    return removed


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
    """Path of the verified library for key, compiling `source` (C text) on a miss."""
    d = cache_dir()
    path = os.path.join(d, key[:40] + suffix)
    if _verified(path, key):
        return path, None
    try:
        os.makedirs(d, exist_ok=True)
        work = tempfile.mkdtemp(prefix='build-', dir=d)
        tmpdir = None
    except OSError:   # read-only or unusable cache: compile in a temporary folder
        work = tmpdir = tempfile.mkdtemp(prefix='lie_dynamics_native_')
    try:
        lib = os.path.join(work, 'k' + suffix)
        t0 = time.perf_counter()
        try:
            _build(source, lib, work, list(flags))
        finally:
            _STATE['seconds'] += time.perf_counter() - t0
        _STATE['compiles'] += 1
        with open(lib, 'rb') as fh:
            body = fh.read()
        with open(lib, 'ab') as fh:
            fh.write(MAGIC + key.encode() + hashlib.sha256(body).hexdigest().encode())
        if tmpdir is not None:
            return lib, tmpdir
        os.replace(lib, path)   # atomic: a concurrent reader sees the old file or the whole new one
        evict(d, cache_max_bytes(), keep=(path,))
        return path, None
    finally:
        if tmpdir is None:
            shutil.rmtree(work, ignore_errors=True)


def _call_module():
    """The extension module of the call path (native_call.c), built or loaded once."""
    with open(os.path.join(HERE, 'native_call.c'), encoding='utf-8') as fh:
        source = fh.read()
    incs = [sysconfig.get_paths()['include'], np.get_include()]
    flags = FLAGS + tuple(f'-I{i}' for i in incs)
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


def library(structure, name, render):
    """The Library of kernel `name` for a model structure (its fingerprint): from the cache,
    else compiled from render() -> (C source, widths, parameter lengths, n_out). None when
    the backend is off or unavailable (module())."""
    if module() is None:
        return None
    key = _key(KERNEL_FLAGS, generator_hash(), structure, name, THRESHOLDS['native_part'])
    path = os.path.join(cache_dir(), key[:40] + '.so')
    for attempt in (0, 1):
        tmp = None
        if not _verified(path, key):
            rendered = render()
            if rendered is None:
                return None
            source, widths, par_lengths, n_out = rendered
            meta = [len(widths), len(par_lengths), n_out, *widths, *par_lengths]
            if len(meta) > 64:
                return None
            meta = ', '.join(str(int(v)) for v in meta)
            source = f'{source}const long lie_meta[64] = {{{meta}}};\n'
            try:
                path, tmp = _compile(source, key, '.so', KERNEL_FLAGS)
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


def bind(lib, params, n_res, out_dims, check=0, rtol=0.0, gil_rows=64):
    """A callable running lib's kernel with these parameter lists (sequences of floats):
    call(*per_state_arrays[, out]) -> result, or None when it declines (native_call.c)."""
    arrays = tuple(np.ascontiguousarray(p, dtype=float).reshape(-1) if len(p) else np.zeros(1) for p in params)
    return module().bind(lib.address, lib.widths, arrays, lib.n_out, n_res, tuple(out_dims), check, rtol, gil_rows,
                         (lib, arrays))
