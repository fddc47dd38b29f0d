"""The dynamics node. This folder is its rclpy shell (`node.py`: the callbacks and the FEATURES
list, `interfaces.py`: the one table of topics, services and QoS, `outputs.py`, `run.py`); the
parts below it are plain Python (no rclpy import, except the feature classes that publish and
the trajectory process's child) and testable without ROS. Imports point down only: core/ imports
nothing else of ros/ (test/test_lint.py checks it).

    core/          the decision core: one sample per joint_states message (cdr), the settings and
                   parameter table (params, settings), the torque command with its ramp, watchdog
                   and diagnostics (compensator, its settings and models: configuration), what became
                   of each message (sample), the fused command path of the common case (fused), the
                   log (log), descriptions into models and the update rule (descriptions), the pipe
                   protocol of the child processes (pipe)
    features/      per-sample features behind one interface (base.Feature): the dynamics topics,
                   the momentum observer and collision flag, the gravity source, payload services
    loading/       robot descriptions: sources, parameter changes, the build process, the loader thread
    trajectories/  ~/trajectory_in -> ~/trajectory_out: serialized trajectories, their effort fill,
                   the trajectory process (the node's side, process; the child, trajectory_process)
"""
