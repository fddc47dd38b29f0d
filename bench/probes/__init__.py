"""One-off investigations whose figures are in docs/benchmarks.md, kept runnable apart from the
benchmarks `python -m bench` runs: `python -m bench.probes.<name>`.

  ab              this tree against another checkout, call by call, in one process
  aba_armature    the ABA kernel's rigid variant (armature zero) beside the armature kernel and pin.aba
  kernel_warm_up  what warming a new model's kernels costs where it is built
  log_line        the node's log line against rclpy's Python logger
  parallel_capacity  two processes against one: the ceiling of a 2-thread speed-up on this machine
  record_gaps     the node's joint_states callback while ~/record records and writes
  node_trace      the dynamics node with its joint_states callbacks and log lines timed (bench.node_loads --trace)
  sched_trace     the kernel's scheduler record of the node's waits for a CPU during bench.node_loads
  latency_split   the round trip cut into DDS, the node's Python to the command, the way back and the work after
  contact_answers  why each wrong or ambiguous isolation answer of bench.contact happens, push by push
"""
