"""lie_dynamics: rigid-body robot dynamics with the Lie-group formulation of
Park, Bobrow & Ploen (1995). The math core imports only numpy and yourdfpy (calibration/ also
scipy and rosbags)."""
import os

from .model.inertia import InertiaWarning
from .model.model import Model
from .model.urdf import URDFWarning, load_urdf

__all__ = ['Model', 'load_urdf', 'default_urdf_path', 'InertiaWarning', 'URDFWarning']

# The folder that holds the package (the repository in a source checkout): without an ament index,
# package://lie_dynamics/... resolves below it, and child processes find the package there.
SOURCE_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def default_urdf_path():
    """Path of the bundled 7-DoF arm (the embedded default)."""
    return os.path.join(os.path.dirname(__file__), 'data', 'arm7.urdf')
