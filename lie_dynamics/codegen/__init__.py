"""Straight-line code by tracing: an algorithm written on scalars becomes a compiled function.

A numpy call costs about a microsecond whatever its size, so one robot state pushed through
stacks of 6x6 matrices is mostly call overhead. Here an algorithm is written once on plain
scalars (Python floats or the tracer's symbols) and traced with the model's constants folded
in: zeros and ones of the home poses, joint axes and masks drop out, repeated
subexpressions are shared, and what remains is emitted as Python source and compiled once
per model structure. The same compiled function runs on Python floats for one state (no
numpy call at all) and on numpy rows with one entry per state for a batch.

  tracer.py   Sym and Graph: the traced scalars, constant folding, shared subexpressions
  render.py   the graph as source: for floats (emit) and for numpy rows (emit_rows)
  crender.py  the graph as C (the native backend), operation for operation as emit
  clanes.py   the graph as C on 4 states at once (vector types), for native batches
  kernel.py   Trace (a traced kernel and its argument roles) and Kernel (the one kernel type:
              the trace and its float, rows and native renderings)
  native.py   the native backend: compiler, loading, binding; native_call.c its call path
              (native_method.c: the Model methods that call it from C; native_command.c: the
              dynamics node's fused command path, ros/core/fused.py)
  disk_cache.py  the native backend's disk cache: names, checks, bound
  algebra.py  3-vectors, 3x3 matrices and spatial algebra on tuples, for tracing
  frames.py   per-structure constants: body frames with every joint axis along z
  thresholds.py  the one threshold table (THRESHOLDS), each entry with its measurement
  runtime.py  the runtime's public names, from:
    cache.py     per-model slots, the shared LRU of kernels, deferred builds
    spec.py      Spec (a kernel's description), Result, the kernels' parameters, accepts
    dispatch.py  call (one algorithm call: fast path, validate once, route, run, deliver), route
    batch.py     the batch runner (run_loop, run_rows)
  traced/     each algorithm's traced form and kernel spec (algorithms/ calls them)
"""
