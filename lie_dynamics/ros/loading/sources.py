"""Where the dynamics node's robot description comes from, in plain Python (no rclpy import).

Three kinds of source: 'topic' (a robot_description topic message, URDF XML), 'parameter'
(the robot_description parameter, URDF XML) and 'file' (urdf_path; `package://` URIs resolve
through the ament index). `Sources` remembers the source of the running model and the last
topic message, and picks what ~/reload_model and an inertia_policy change reload.
"""
import os
from ... import SOURCE_ROOT


def resolve_path(path):
    """`package://PKG/rel` -> the installed share directory of PKG (ament index); for this
    package also the source tree when it is not installed with colcon. Other paths unchanged."""
    if not path.startswith('package://'):
        return path
    pkg, _, rel = path[len('package://'):].partition('/')
    try:
        from ament_index_python.packages import get_package_share_directory
        candidate = os.path.join(get_package_share_directory(pkg), rel)
        if os.path.exists(candidate):
            return candidate
    except Exception:  # package or ament index unknown: try the source tree below
        pass
    if pkg == 'lie_dynamics':
        candidate = os.path.join(SOURCE_ROOT, rel)
        if os.path.exists(candidate):
            return candidate
    raise ValueError(f'cannot resolve {path!r} (package not found in AMENT_PREFIX_PATH)')


def source_label(kind, text):
    """How the log and the diagnostics name a source."""
    return {'topic': 'topic robot_description', 'parameter': 'parameter robot_description',
            'file': f'file {text}'}[kind]


def open_source(kind, text):
    """(what load_urdf reads, label) of a source. Raises ValueError: a topic or parameter text
    that is not URDF XML, a `package://` path that does not resolve."""
    label = source_label(kind, text)
    if kind != 'file' and not text.lstrip().startswith('<'):
        raise ValueError('not URDF XML')
    source = resolve_path(text) if kind == 'file' else text
    return source, (label if source == text else f'{label} ({source})')


class Sources:
    """The source of the running model and the last robot_description topic message."""

    def __init__(self):
        self.current = None     # (kind, text) of the running model; text of a file: its path
        self.topic_xml = None   # last message on the robot_description topic

    def reload_source(self, parameter_xml, urdf_path):
        """(kind, text) to reload: the running model's source as it is now (the last topic
        message, the robot_description parameter's value, or the file); before any model
        loaded, the last topic message, else the parameters. (None, None) if there is none."""
        if self.current is not None:
            kind, text = self.current
            if kind == 'topic':
                text = self.topic_xml
            elif kind == 'parameter':
                text = parameter_xml
            return (kind, text) if text else (None, None)
        for kind, text in (('topic', self.topic_xml), ('parameter', parameter_xml), ('file', urdf_path)):
            if text:
                return kind, text
        return None, None
