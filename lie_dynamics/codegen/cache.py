"""What the runtime keeps: one slot per live model, one shared LRU of kernels, deferred builds.

Compiled code depends only on a model's structure (home poses, screws, tree, mimic map), so
it is cached by a fingerprint of that structure in one bounded LRU shared by all models:
copies of a model, and models loaded from the same URDF, share their kernels. What changes
at run time (inertias and payloads, gravity, locked-joint values) is cached per model until
the model's version changes (every setter bumps it). A thread inside `deferred` (a control
path) never builds kernel code: until another thread has built it (`build`), its calls take
the reference.
"""
import collections
import hashlib
import threading
import weakref

import numpy as np

from . import native as _native
from . import looped as _looped
from .frames import Frames
from .kernel import Kernel, builds as _kernel_builds
from .thresholds import THRESHOLDS


class Slot:
    """What the runtime keeps for one live model (dropped with it): its fingerprint, Frames and
    kernels (structure, never invalidated) and what follows the model's version: `values`
    (derived values and bound kernels), `fast` (the fast path per Spec), `natives` (the bound
    native kernels per Spec). A kernel the model has not is kept as False (asked once)."""
    __slots__ = ('ref', 'version', 'fingerprint', 'frames', 'kernels', 'structure', 'values', 'fast', 'natives')

    def __init__(self, model):
        self.ref = weakref.ref(model)
        self.version, self.fingerprint, self.frames = None, None, None
        self.kernels, self.structure, self.values, self.fast, self.natives = {}, {}, {}, {}, {}


SLOTS = {}                                    # id(model) -> Slot, removed when the model dies
_SHARED = collections.OrderedDict()           # (fingerprint, name) -> kernel or Frames, LRU
_LOCK = threading.Lock()
_BUILDS = [0]


def slot(model):
    """The model's Slot, its version-dependent entries emptied when the model's version changed.
    (The hot paths inline the lookup: SLOTS.get(id(model)), checked as here.)"""
    s = SLOTS.get(id(model))
    if s is None or s.ref() is not model:
        s = SLOTS[id(model)] = Slot(model)
        weakref.finalize(model, SLOTS.pop, id(model), None)
    if s.version != model.version:
        s.values, s.fast, s.natives = {}, {}, {}   # new dicts: concurrent readers keep the old ones
        s.version = model.version
    return s


def _shared(key, make):
    """The LRU entry `key`, made on a miss (outside the lock: builds take long); `_BUILDS`
    counts the Frames made (kernels count their renderings: kernel.builds)."""
    with _LOCK:
        v = _SHARED.get(key)
        if v is not None:
            _SHARED.move_to_end(key)
            return v
    v = make()
    with _LOCK:
        _BUILDS[0] += isinstance(v, Frames)
        v = _SHARED.setdefault(key, v)
        while len(_SHARED) > THRESHOLDS['compiled_cache']:
            _SHARED.popitem(last=False)
    return v


def cache_info():
    """dict(builds=kernels rendered and Frames built since the process started, cached=entries
    in the shared cache, models=live models with runtime state)."""
    return dict(builds=_BUILDS[0] + _kernel_builds(), cached=len(_SHARED), models=len(SLOTS))


def clear():
    """Forget every compiled kernel and cached value (live models rebuild on next use)."""
    with _LOCK:
        _SHARED.clear()
    SLOTS.clear()
    _native.invalidate()


def forget(model):
    """Drop what the runtime keeps for this model (e.g. after changing THRESHOLDS); its
    kernels come back from the shared cache."""
    SLOTS.pop(id(model), None)
    _native.invalidate()


def derived(model, key, compute):
    """compute(), cached for the model until its version changes (a setter ran)."""
    s = slot(model)
    v = s.values.get(key)
    if v is None:
        v = s.values[key] = compute()
    return v


def structural(model, key, compute):
    """compute(), cached for the model's lifetime (it may only depend on the structure)."""
    s = slot(model)
    v = s.structure.get(key)
    if v is None:
        v = s.structure[key] = compute()
    return v


def pairs(model):
    """(body, ancestor-or-self) pairs: the sum of the body depths (the regressor's size)."""
    return structural(model, 'pairs', lambda: int(model.depth.sum()))


def size(model, limits):
    """The model's size as THRESHOLDS entry `limits` counts it: bodies or (body, ancestor) pairs."""
    return model.nb if limits.size == 'bodies' else pairs(model)


def fingerprint(model):
    """Hash of everything a kernel's source depends on (copies of a model share kernels)."""
    s = slot(model)
    if s.fingerprint is None:
        h = hashlib.sha1()
        for a in (model.M, model.S, model.parent, model.E, model.L != 0, model.c0 != 0):
            h.update(np.ascontiguousarray(a).tobytes())
            h.update(str(np.shape(a)).encode())
        s.fingerprint = h.hexdigest()
    return s.fingerprint


def frames(model):
    """The model's Frames (shared by models of the same structure)."""
    s = slot(model)
    if s.frames is None:
        s.frames = _shared((fingerprint(model), 'frames'), lambda: Frames(model))
    return s.frames


def native_max(limits):
    """The size cap of a THRESHOLDS entry's native kernels (its compile_max unless set)."""
    return limits.compile_max if limits.native_max is None else limits.native_max


def python_sized(model, spec):
    """Whether spec's Python forms may be built for this model (its size within compile_max;
    above it, up to native_max, the kernel exists for its C form only)."""
    return size(model, THRESHOLDS[spec.limits]) <= THRESHOLDS[spec.limits].compile_max


def entry(model, spec):
    """spec's Kernel of this model's structure (created, not traced: kernel.Kernel), or None:
    too large for THRESHOLDS (compile_max, or native_max where the native backend is wanted),
    spec.supports(model) false, or screws other than unit revolute / prismatic axes."""
    s = slot(model)
    k = s.kernels.get(spec.name)
    if k is None:
        t = THRESHOLDS[spec.limits]
        loop = looped(model, spec)
        if (not loop and size(model, t) > (max(t.compile_max, native_max(t)) if native_on(model) else t.compile_max)) \
                or (spec.supports is not None and not spec.supports(model)) or not frames(model).supported:
            k = False
        else:
            fr, fp = frames(model), fingerprint(model)
            name = spec.name + (':looped' if loop else '')
            k = _shared((fp, name), lambda: Kernel(lambda: spec.build(fr), spec.name, fr, fp,
                                                   (lambda: spec.looped(fr)) if loop else None))
        s.kernels[spec.name] = k
    return k or None


def looped(model, spec):
    """Whether spec's kernel for this model is its looped native form (codegen/looped.py): the
    native backend on, the model's size (counted as THRESHOLDS[spec.limits].looped_size) from its
    looped_from or above the straight-line kernel's caps (compile_max, native_max), a model the
    looped drivers take (each joint one body, no mimic joints: looped.joints_of)."""
    t = THRESHOLDS[spec.limits]
    if spec.looped is None or t.looped_from is None or not native_on(model):
        return False
    sized = size(model, t._replace(size=t.looped_size or t.size)) >= t.looped_from
    if not sized and size(model, t) <= max(t.compile_max, native_max(t)):
        return False
    fr = frames(model)
    return fr.supported and structural(model, 'looped_joints', lambda: _looped.joints_of(fr) is not None)


def native_on(model):
    """Whether this model may use the native kernels (the backend wanted, not use_native(False))."""
    return _native.wanted() and not slot(model).structure.get('native_off')


def use_native(model, on=True):
    """Let this model use the native kernels (the default) or only the Python ones (on=False:
    for comparisons in one process; LIE_DYNAMICS_NATIVE=0 switches them off everywhere)."""
    s = slot(model)
    s.structure['native_off'] = not on
    s.natives, s.fast, s.values = {}, {}, {}   # values: derived entries that hold a bound native kernel
    _native.invalidate()
    s.kernels = {}   # which kernels exist depends on the backend (THRESHOLDS native_max)


# ---------------------------------------------------------------------------- deferred builds
_DEFER = threading.local()


class deferred:
    """`with deferred(request):` this thread builds no kernel code: a call whose kernel is not
    built yet (its C library not loaded, its Python forms not made) takes the algorithm's
    reference path, and request(model, spec) asks for the build, which `build` does in another
    thread. For a control path: generating and compiling a kernel takes up to seconds, the
    reference answers at once. One instance may be entered again, by any thread (a class, not a
    generator: a control path enters it per message, in about a tenth of a microsecond)."""
    __slots__ = ('request',)

    def __init__(self, request):
        self.request = request

    def __enter__(self):
        stack = getattr(_DEFER, 'stack', None)
        if stack is None:
            stack = _DEFER.stack = []
        stack.append(getattr(_DEFER, 'request', None))
        _DEFER.request = self.request
        return self

    def __exit__(self, *exc):
        _DEFER.request = _DEFER.stack.pop()
        return False


def later(model, spec, python=True):
    """True when this thread defers builds (`deferred`) and spec's kernel for this model is not
    built (python False: its C library only); its build is then requested."""
    request = getattr(_DEFER, 'request', None)
    if request is None:
        return False
    k = entry(model, spec)
    if k is None or k.built(native_on(model), python and python_sized(model, spec)):
        return False
    request(model, spec)
    return True


def build(model, spec):
    """Build spec's kernel code for this model (what a deferred call requested): its C library
    where the native backend works, else its Python forms."""
    k = entry(model, spec)
    if k is not None and not (native_on(model) and k.native()) and python_sized(model, spec):
        k.python()
