"""`python -m lie_dynamics.dynamics_node`: the dynamics node (lie_dynamics.ros.node), kept at its
documented path."""
import sys

from .ros.node import DynamicsNode, main  # noqa: F401

if __name__ == '__main__':
    sys.exit(main())
