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
1008 policy violation, 1009 message too big) so both sides map errors the same way.
"""
from __future__ import annotations


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
        from protocol.messages import ErrorCode  # messages imports this module

        name = ErrorCode(code).name if code in ErrorCode._value2member_map_ else str(code)
        super().__init__(f"peer error {name}: {text}")
        self.code = code
        self.text = text
