"""lie_dynamics: rigid-body robot dynamics with the Lie-group formulation of
Park, Bobrow & Ploen (1995). The math core imports only numpy and yourdfpy."""
from .model.inertia import InertiaWarning
from .model.model import Model
from .model.urdf import URDFWarning, load_urdf

__all__ = ['Model', 'load_urdf', 'default_urdf_path', 'InertiaWarning', 'URDFWarning']


def default_urdf_path():
    """Path of the bundled 7-DoF arm (the embedded default)."""
    import os
    return os.path.join(os.path.dirname(__file__), 'data', 'arm7.urdf')
