"""`python -m lie_dynamics.demo` (what `make demo` runs): the documented module path of the `demo`
executable, a thin alias of lie_dynamics.sim.demo (which implements it), named like the executable."""
import sys

from .sim.demo import main

__all__ = ['main']

if __name__ == '__main__':
    sys.exit(main())
