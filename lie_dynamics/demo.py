"""`python -m lie_dynamics.demo`: the embedded default (lie_dynamics.sim.demo), kept at its
documented path."""
import sys

from .sim.demo import main

if __name__ == '__main__':
    sys.exit(main())
