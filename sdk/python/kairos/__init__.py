"""Kairos robot client for Python: the Rust SDK (kairos-sdk) behind a small Pythonic API.

    import kairos
    client = kairos.Client.from_data_dir("kairos-data", "127.0.0.1:4433")
    actions = client.infer({"state": state, "images": {"front": rgb}, "instruction": "pick"})

See kairos/__init__.pyi for the API and docs/CLIENTS.md for how it compares with the other
clients.
"""

from kairos._kairos import (
    Client,
    ConnectionFailed,
    InvalidObservation,
    InvalidRequest,
    KairosError,
    Overloaded,
    PinMismatch,
    ProtocolError,
    ServerError,
    TaskError,
    Timeout,
    Unauthorized,
    __version__,
)

__all__ = [
    "Client",
    "ConnectionFailed",
    "InvalidObservation",
    "InvalidRequest",
    "KairosError",
    "Overloaded",
    "PinMismatch",
    "ProtocolError",
    "ServerError",
    "TaskError",
    "Timeout",
    "Unauthorized",
    "__version__",
]
