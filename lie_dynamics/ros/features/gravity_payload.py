"""The documented import path of the gravity topic and payload services features, which live in
gravity_topic.py and payload_services.py."""
from .gravity_topic import GravityTopic
from .payload_services import PayloadServices

__all__ = ['GravityTopic', 'PayloadServices']
