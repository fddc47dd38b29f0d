"""`lie_dynamics.identification` and `python -m lie_dynamics.identification`: inertial-parameter
identification (lie_dynamics.algorithms.identification), kept at its documented path."""

from .algorithms.identification import (IdentificationResult, UnidentifiableWarning,  # noqa: F401
                                         excitation_trajectory, identify, main)

if __name__ == '__main__':
    main()
