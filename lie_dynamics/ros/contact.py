"""`lie_dynamics.ros.contact.motor_torque`: the path docs/node.md gave before the function moved to
ros/features/contact.py (where the docs point now), kept importable: code outside the package may use it."""
from .features.contact import motor_torque

__all__ = ['motor_torque']
