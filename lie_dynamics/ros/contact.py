"""The documented path of `motor_torque` (docs/node.md); the observer lives in features/contact.py."""
from .features.contact import motor_torque  # noqa: F401
