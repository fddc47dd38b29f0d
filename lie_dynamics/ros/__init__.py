"""The dynamics node. This folder is its rclpy shell (`node.py`: the callbacks and the FEATURES
list, `interfaces.py`: the one table of topics, services and QoS, `outputs.py`, `run.py`, and
`trajectory_process.py`, the child process serving ~/trajectory_in); the parts below it are
plain Python (no rclpy import, except the feature classes that publish) and testable without ROS:

    core/          the decision core: one sample per joint_states message (cdr), the settings and
                   parameter table (params, settings), the torque command with its ramp, watchdog
                   and diagnostics (compensator), what became of each message (sample), the log (log)
    features/      per-sample features behind one interface (base.Feature): the dynamics topics,
                   the momentum observer and collision flag, the gravity source, payload services
    loading/       robot descriptions: sources, the update policy, the build process, the loader thread
    trajectories/  ~/trajectory_in -> ~/trajectory_out: serialized trajectories, their effort fill,
                   the node's side of the trajectory process
"""
