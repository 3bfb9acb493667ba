"""OpenIGTLink service: probe TRANSFORM in; lesion POINT, TRANSFORM, POLYDATA, STRING out.

``protocol`` frames bytes, ``messages`` registers the message types, ``replies`` and
``commands`` build what is sent, ``session`` decides it (no sockets), ``server`` moves the bytes
and ``service`` runs ``biopsynav serve`` (docs/igtl.md).
"""

from .protocol import IgtlProtocolError, MessageReader, read_message
from .server import IgtlServer
from .service import run_service, serve
from .session import IgtlSession, ServerStats, TrackerLike

__all__ = ["IgtlProtocolError", "IgtlServer", "IgtlSession", "MessageReader",
           "ServerStats", "TrackerLike", "read_message", "run_service",
           "serve"]
