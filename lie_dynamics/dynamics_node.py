"""`python -m lie_dynamics.dynamics_node`: the documented module path of the `dynamics_node`
executable, a thin alias of lie_dynamics.ros.node (which implements it), named like the executable."""
import sys

from .ros.node import DynamicsNode, main

__all__ = ['DynamicsNode', 'main']

if __name__ == '__main__':
    sys.exit(main())
