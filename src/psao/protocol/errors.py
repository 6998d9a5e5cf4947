"""Errors of the shared protocol package.

    ProtocolError                 anything malformed on the wire or in a shared format
    ├── HeaderError               bad magic, version, type, codec or length in a message header
    ├── LimitError                a length or decompressed size above its limit
    ├── PayloadError              a payload that does not parse as its message type says
    ├── CodecError                a codec not offered, or a compressed frame that does not decode
    ├── RefusedError              a well-formed request the server will not serve (scene, token, full, edits)
    ├── EditError                 a SceneEdit of an unknown instance or with a transform out of range
    ├── UnexpectedMessage         a valid message where the conversation does not allow it
    └── RemoteError               the peer sent an Error message

Each carries a websocket close code (RFC 6455: 1002 protocol error, 1003 unsupported data,
1008 policy violation, 1009 message too big) so both sides map errors the same way. ErrorCode is the
code an Error message carries.
"""
from __future__ import annotations

from enum import IntEnum


class ErrorCode(IntEnum):
    """Error message codes; each names the reason a connection is closed."""

    INTERNAL = 1
    BAD_HEADER = 2
    TOO_LARGE = 3
    BAD_PAYLOAD = 4
    BAD_CODEC = 5
    UNEXPECTED_MESSAGE = 6
    SCENE_MISMATCH = 7
    UNAUTHORIZED = 8
    SHUTTING_DOWN = 9
    TIMEOUT = 10
    SERVER_FULL = 11  # the server has as many connections as it serves; try later
    EDITS_NOT_ALLOWED = 12  # SceneEdit from a connection without the edit token (or edits off)
    BAD_EDIT = 13  # SceneEdit of an unknown instance or with a transform out of the allowed range


class ProtocolError(Exception):
    close_code = 1002


class HeaderError(ProtocolError):
    close_code = 1002


class LimitError(ProtocolError):
    close_code = 1009


class PayloadError(ProtocolError):
    close_code = 1002


class CodecError(ProtocolError):
    close_code = 1003


class RefusedError(ProtocolError):
    """A well-formed request the server will not serve: wrong scene, missing or wrong token."""

    close_code = 1008

    def __init__(self, text: str, code: int, close_code: int | None = None):
        super().__init__(text)
        self.code = code
        if close_code is not None:
            self.close_code = close_code


class EditError(ProtocolError):
    """A SceneEdit the server cannot apply: unknown instance, or a transform out of the allowed range."""

    close_code = 1008


class UnexpectedMessage(ProtocolError):
    """A valid message at a point of the conversation where it is not allowed."""

    close_code = 1002


class RemoteError(ProtocolError):
    """The peer sent an Error message."""

    def __init__(self, code: int, text: str):
        name = ErrorCode(code).name if code in ErrorCode._value2member_map_ else str(code)
        super().__init__(f"peer error {name}: {text}")
        self.code = code
        self.text = text
