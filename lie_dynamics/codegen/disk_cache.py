"""The native backend's disk cache: where compiled libraries live, how they are named, checked and bounded.

Folder: $LIE_DYNAMICS_CACHE_DIR, else $XDG_CACHE_HOME/lie_dynamics, else ~/.cache/lie_dynamics.
A file is named by a hash of everything that determines it (`key`: native.py passes the
generator's own source, the model structure, kernel name and THRESHOLDS['native_part'], or the
call path's C source, with the compiler, its flags and the Python/numpy versions), so a cached
kernel loads without being traced. Every file ends with a trailer (MAGIC, its key, the SHA-256
of the bytes before it), checked before loading (`verified`): a truncated or foreign file is
rebuilt, never loaded. Files are written to a temporary name and renamed into place (`store`:
two processes compiling the same kernel both succeed); an unwritable cache folder means
compiling in a temporary folder, removed after loading (`work_folder`). The folder is bounded:
$LIE_DYNAMICS_CACHE_MAX_MB (default CACHE_MAX_MB); a file's time is its last use, and after
each compile the least recently used files go until the folder holds 3/4 of the bound (`evict`).
"""
import functools
import glob
import hashlib
import os
import shutil
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
MAGIC = b'\nlie_dynamics native '
_TRAILER = len(MAGIC) + 64 + 64
CACHE_MAX_MB = 512.0   # about ten times what a busy development machine collects
STALE_BUILD_S = 3600.0  # a build folder this old belongs to a process that died while compiling


def cache_dir():
    d = os.environ.get('LIE_DYNAMICS_CACHE_DIR')
    if d:
        return d
    base = os.environ.get('XDG_CACHE_HOME') or os.path.join(os.path.expanduser('~'), '.cache')
    return os.path.join(base, 'lie_dynamics')


@functools.lru_cache(maxsize=1)
def generator_hash():
    """Hash of the source that determines the C kernels (the tracer, renderers, traced forms, and
    laws.py, whose friction law the observer's step traces)."""
    h = hashlib.sha256()
    for path in sorted(glob.glob(os.path.join(HERE, '*.py')) + glob.glob(os.path.join(HERE, 'traced', '*.py'))
                       + [os.path.join(os.path.dirname(HERE), 'laws.py')]):
        with open(path, 'rb') as fh:
            h.update(os.path.basename(path).encode() + fh.read())
    h.update(f'{sys.version_info[:2]} {np.__version__}'.encode())
    return h.hexdigest()


def key(*parts):
    """The hash naming a file of the cache: every part that determines its content."""
    h = hashlib.sha256()
    for p in parts:
        h.update(str(p).encode() + b'\0')
    return h.hexdigest()


def path_of(k, suffix):
    return os.path.join(cache_dir(), k[:40] + suffix)


def verified(path, k):
    """True when path ends with the trailer of key k and the SHA-256 of the bytes before it;
    its time is then set to now (its last use, which `evict` reads)."""
    try:
        with open(path, 'rb') as fh:
            data = fh.read()
    except OSError:
        return False
    if len(data) <= _TRAILER or not data.endswith(MAGIC + k.encode() + hashlib.sha256(data[:-_TRAILER]).hexdigest()
                                                  .encode()):
        return False
    try:
        os.utime(path)
    except OSError:   # a read-only cache is still used
        pass
    return True


def work_folder():
    """(folder to compile in, temporary folder to remove after loading or None): a build folder
    inside the cache, or, when the cache is read-only or unusable, a temporary folder."""
    d = cache_dir()
    try:
        os.makedirs(d, exist_ok=True)
        return tempfile.mkdtemp(prefix='build-', dir=d), None
    except OSError:
        tmp = tempfile.mkdtemp(prefix='lie_dynamics_native_')
        return tmp, tmp


def store(lib, k, suffix, temporary):
    """Sign the compiled file `lib` with the trailer of key k and move it into the cache (then
    bound the folder); `temporary`: the cache is unusable, lib stays where it is. Its path."""
    with open(lib, 'rb') as fh:
        body = fh.read()
    with open(lib, 'ab') as fh:
        fh.write(MAGIC + k.encode() + hashlib.sha256(body).hexdigest().encode())
    if temporary:
        return lib
    path = path_of(k, suffix)
    os.replace(lib, path)   # atomic: a concurrent reader sees the old file or the whole new one
    evict(cache_dir(), cache_max_bytes(), keep=(path,))
    return path


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
