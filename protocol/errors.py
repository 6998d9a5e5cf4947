"""Errors of the shared protocol package.

    ProtocolError                 anything malformed on the wire or in a shared format
    ├── HeaderError               bad magic, version, type, codec or length in a message header
    ├── LimitError                a length or decompressed size above its limit
    ├── PayloadError              a payload that does not parse as its message type says
    └── CodecError                a codec not offered, or a compressed frame that does not decode

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
