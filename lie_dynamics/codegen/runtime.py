"""Running the generated kernels: one cache, one threshold table, one dispatch, one batch runner.

The runtime's public names, in four modules:

  * cache.py: what the runtime keeps. Compiled code depends only on a model's structure, so it
    is cached by a fingerprint of that structure in one bounded LRU shared by all models; what
    changes at run time (inertias and payloads, gravity, locked-joint values) enters the
    kernels as parameter lists, cached per model until the model's version changes (every
    setter bumps it). A thread inside `deferred` (a control path) never builds kernel code:
    until another thread has built it (`build`), its calls take the reference.
  * spec.py: a kernel's description (`Spec`: how to build it from the model's Frames, which
    parameter lists follow the per-state arguments, which entry of THRESHOLDS says when it
    runs, and its `Result`: how its outputs are read and accepted), its parameters and `accepts`.
  * dispatch.py: one call of an algorithm, `call` (fast path, validate once, route, kernel,
    accept, deliver); `route`, the one dispatch decision: the float kernel (one state, or a
    small batch state by state), the kernel on numpy rows (a large batch), or None: the
    algorithm's vectorised reference.
  * batch.py: the batch runner (`run_loop`, `run_rows`).
"""
from .batch import run_loop, run_rows
from .cache import (build, cache_info, clear, deferred, derived, fingerprint, forget, frames, looped, native_max,
                    native_on, pairs, structural, use_native)
from .dispatch import (Entry, Output, call, check_mode, check_out, deliver, evaluate, fast, native, native_first,
                       native_keyed, route, run)
from .spec import PARAMETERS, Bound, Result, Spec, accepts, as_rows, kernel, parameter, params, result_of
from .thresholds import THRESHOLDS
from ..validation import float_list as is_fast_single   # its name in earlier versions

__all__ = ['run_loop', 'run_rows', 'build', 'cache_info', 'clear', 'deferred', 'derived', 'fingerprint', 'forget',
           'frames', 'looped', 'native_max', 'native_on', 'pairs', 'structural', 'use_native', 'Entry', 'Output',
           'call',
           'check_mode', 'check_out', 'deliver', 'evaluate', 'fast', 'native', 'native_first', 'native_keyed',
           'route', 'run',
           'PARAMETERS', 'Bound', 'Result', 'Spec', 'accepts', 'as_rows', 'kernel', 'parameter', 'params',
           'result_of', 'THRESHOLDS',
           'is_fast_single']
