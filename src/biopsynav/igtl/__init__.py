"""OpenIGTLink service: probe TRANSFORM in, lesion POINT/TRANSFORM/STRING out (docs/igtl.md)."""

from .protocol import IgtlProtocolError, MessageReader, read_message
from .rigid import RigidLesionTracker
from .server import IgtlServer, ServerStats, TrackerLike, run_service, serve

__all__ = ["IgtlProtocolError", "IgtlServer", "MessageReader", "RigidLesionTracker",
           "ServerStats", "TrackerLike", "read_message", "run_service", "serve"]
