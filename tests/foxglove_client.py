"""A minimal Foxglove WebSocket client for tests: RFC 6455 over a plain socket, Foxglove's WebSocket protocol.

It does what Foxglove's app does on connecting, nothing borrowed from the
server's package: the HTTP upgrade offering the protocol's two subprotocol
names, `foxglove.websocket.v1` and `foxglove.sdk.v1` (the same protocol
renamed; foxglove-sdk servers accept only the new name), the server's
`Sec-WebSocket-Accept` and chosen subprotocol checked, then the `serverInfo`
and `advertise` JSON messages, a `subscribe` for channels, and the binary
`messageData` frames (opcode 1: subscription id u32, log time u64 ns, payload),
decoded by the channel's encoding: `json`, or `protobuf` read with the field
numbers of the channel's own schema (a FileDescriptorSet) by a wire-format
reader written here.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import json
import os
import socket
import struct
import time
from dataclasses import dataclass, field
from typing import Any

SUBPROTOCOLS = ("foxglove.websocket.v1", "foxglove.sdk.v1")
WS_GUID = "258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
OP_TEXT, OP_BINARY, OP_CLOSE, OP_PING, OP_PONG = 1, 2, 8, 9, 10


# ---------------------------------------------------------------- protobuf wire format


def _varint(buf: bytes, pos: int) -> tuple[int, int]:
    out = shift = 0
    while True:
        b = buf[pos]
        pos += 1
        out |= (b & 0x7F) << shift
        if not b & 0x80:
            return out, pos
        shift += 7


def proto_fields(buf: bytes) -> list[tuple[int, int, Any]]:
    """(field number, wire type, value) of one protobuf message: ints for varint/fixed, bytes else."""
    out: list[tuple[int, int, Any]] = []
    pos = 0
    while pos < len(buf):
        key, pos = _varint(buf, pos)
        num, wire = key >> 3, key & 7
        value: int | bytes
        if wire == 0:
            value, pos = _varint(buf, pos)
        elif wire == 1:
            value, pos = struct.unpack_from("<Q", buf, pos)[0], pos + 8
        elif wire == 2:
            n, pos = _varint(buf, pos)
            value, pos = buf[pos : pos + n], pos + n
        elif wire == 5:
            value, pos = struct.unpack_from("<I", buf, pos)[0], pos + 4
        else:
            raise ValueError(f"protobuf wire type {wire} not supported")
        out.append((num, wire, value))
    return out


def schema_messages(descriptor_set: bytes) -> dict[str, dict[str, tuple[int, str]]]:
    """Message name -> field name -> (number, type name or '') from a FileDescriptorSet."""
    out: dict[str, dict[str, tuple[int, str]]] = {}
    for num, _, file in proto_fields(descriptor_set):
        if num != 1:  # FileDescriptorSet.file
            continue
        package = next((v.decode() for n, _, v in proto_fields(file) if n == 2), "")
        for n, _, msg in proto_fields(file):
            if n != 4:  # FileDescriptorProto.message_type
                continue
            parts = proto_fields(msg)
            name = next(v.decode() for k, _, v in parts if k == 1)
            fields: dict[str, tuple[int, str]] = {}
            for k, _, f in parts:
                if k == 2:  # DescriptorProto.field
                    fp = {a: v for a, _, v in proto_fields(f)}
                    fields[fp[1].decode()] = (fp[3], fp.get(6, b"").decode().lstrip("."))
            out[f"{package}.{name}" if package else name] = fields
    return out


def decode_proto(buf: bytes, message: str, schema: dict[str, dict[str, tuple[int, str]]]) -> dict[str, Any]:
    """A protobuf message as a dict by the schema's field names (nested messages decoded, repeated as lists)."""
    by_number = {num: (name, sub) for name, (num, sub) in schema[message].items()}
    out: dict[str, Any] = {}
    for num, _, value in proto_fields(buf):
        if num not in by_number:
            continue
        name, sub = by_number[num]
        decoded = decode_proto(value, sub, schema) if sub in schema else value
        if name in out:
            out[name] = [*out[name], decoded] if isinstance(out[name], list) else [out[name], decoded]
        else:
            out[name] = decoded
    return out


# ---------------------------------------------------------------- the WebSocket client


@dataclass
class Channel:
    id: int
    topic: str
    encoding: str
    schema_name: str
    schema: bytes | str


@dataclass
class FoxgloveClient:
    """A connected client; `messages[topic]` collects decoded messages of subscribed channels."""

    sock: socket.socket
    server_info: dict[str, Any] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    subscriptions: dict[int, int] = field(default_factory=dict)  # subscription id -> channel id
    messages: dict[str, list[Any]] = field(default_factory=dict)
    subprotocol: str = ""
    closed: bytes | None = None  # the server's close frame payload (status code, reason), once it closed
    _buf: bytes = b""

    @classmethod
    def connect(cls, host: str, port: int, timeout_s: float = 10.0) -> FoxgloveClient:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                sock = socket.create_connection((host, port), timeout=2.0)
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.1)
        key = base64.b64encode(os.urandom(16)).decode()
        request = (
            f"GET / HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
            f"Sec-WebSocket-Protocol: {', '.join(SUBPROTOCOLS)}\r\n\r\n"
        )
        sock.sendall(request.encode())
        client = cls(sock)
        head = client._read_until(b"\r\n\r\n").decode("latin-1")
        status, *lines = head.split("\r\n")
        headers = {k.strip().lower(): v.strip() for k, _, v in (ln.partition(":") for ln in lines if ln)}
        accept = base64.b64encode(hashlib.sha1((key + WS_GUID).encode()).digest()).decode()
        if " 101 " not in status + " " or headers.get("sec-websocket-accept") != accept:
            raise ConnectionError(f"no WebSocket upgrade: {status!r} {headers}")
        client.subprotocol = headers.get("sec-websocket-protocol", "")
        if client.subprotocol not in SUBPROTOCOLS:
            raise ConnectionError(f"server chose subprotocol {client.subprotocol!r}")
        return client

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self._send(OP_CLOSE, struct.pack(">H", 1000))
        self.sock.close()

    # ---- frames

    def _read_until(self, marker: bytes) -> bytes:
        while marker not in self._buf:
            chunk = self.sock.recv(65536)
            if not chunk:
                raise ConnectionError("server closed the connection")
            self._buf += chunk
        head, _, self._buf = self._buf.partition(marker)
        return head

    def _read_exact(self, n: int) -> bytes:
        while len(self._buf) < n:
            chunk = self.sock.recv(max(65536, n - len(self._buf)))
            if not chunk:
                raise ConnectionError("server closed the connection")
            self._buf += chunk
        out, self._buf = self._buf[:n], self._buf[n:]
        return out

    def _send(self, opcode: int, payload: bytes) -> None:
        """One masked frame (clients must mask, RFC 6455 5.3)."""
        mask = os.urandom(4)
        n = len(payload)
        head = bytes([0x80 | opcode])
        if n < 126:
            head += bytes([0x80 | n])
        elif n < 1 << 16:
            head += bytes([0x80 | 126]) + struct.pack(">H", n)
        else:
            head += bytes([0x80 | 127]) + struct.pack(">Q", n)
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
        self.sock.sendall(head + mask + masked)

    def _frame(self) -> tuple[int, bytes]:
        """The next whole message (continuation frames joined); pings answered."""
        opcode, parts = 0, []
        while True:
            b0, b1 = self._read_exact(2)
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._read_exact(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._read_exact(8))[0]
            mask = self._read_exact(4) if b1 & 0x80 else b""
            data = self._read_exact(n)
            if mask:
                data = bytes(b ^ mask[i % 4] for i, b in enumerate(data))
            op = b0 & 0x0F
            if op == OP_PING:
                self._send(OP_PONG, data)
                continue
            if op in (OP_TEXT, OP_BINARY, OP_CLOSE):
                opcode = op
            parts.append(data)
            if b0 & 0x80:
                return opcode, b"".join(parts)

    # ---- the Foxglove protocol

    def send_json(self, obj: dict[str, Any]) -> None:
        self._send(OP_TEXT, json.dumps(obj).encode())

    def subscribe_all(self) -> None:
        """Subscribe to every advertised channel not yet subscribed."""
        subs = []
        done = set(self.subscriptions.values())
        for ch in self.channels.values():
            if ch.id not in done:
                sub_id = len(self.subscriptions) + 1
                self.subscriptions[sub_id] = ch.id
                subs.append({"id": sub_id, "channelId": ch.id})
        if subs:
            self.send_json({"op": "subscribe", "subscriptions": subs})

    def poll(self, timeout_s: float) -> None:
        """Read frames for `timeout_s` or until the server closes: advertisements recorded, message data
        decoded into `messages`."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and self.closed is None:
            self.sock.settimeout(max(0.01, deadline - time.monotonic()))
            try:
                opcode, data = self._frame()
            except TimeoutError:
                return
            if opcode == OP_CLOSE:
                self.closed = data
                return
            if opcode == OP_TEXT:
                self._control(json.loads(data))
            elif data and data[0] == 1:  # messageData
                sub_id, _log_time_ns = struct.unpack_from("<IQ", data, 1)
                ch = self.channels[self.subscriptions[sub_id]]
                self.messages.setdefault(ch.topic, []).append(self.decode(ch, data[13:]))

    def _control(self, msg: dict[str, Any]) -> None:
        op = msg.get("op")
        if op == "serverInfo":
            self.server_info = msg
        elif op == "advertise":
            for c in msg["channels"]:
                schema = c.get("schema", "")
                if c["encoding"] == "protobuf":
                    schema = base64.b64decode(schema)
                self.channels[c["id"]] = Channel(c["id"], c["topic"], c["encoding"], c["schemaName"], schema)
        elif op == "unadvertise":
            for cid in msg["channelIds"]:
                self.channels.pop(cid, None)

    @staticmethod
    def decode(ch: Channel, payload: bytes) -> Any:
        if ch.encoding == "json":
            return json.loads(payload)
        if ch.encoding == "protobuf":
            assert isinstance(ch.schema, bytes)
            return decode_proto(payload, ch.schema_name, schema_messages(ch.schema))
        raise ValueError(f"{ch.topic}: encoding {ch.encoding!r} not decoded by this client")


def main() -> None:
    """`python -m tests.foxglove_client PORT`: connect, subscribe to every channel, decode every message
    until the server closes; print the messages decoded per channel as JSON (bench/bench_capture.py runs
    it as its own process, as Foxglove's app would be)."""
    import sys

    client = FoxgloveClient.connect("127.0.0.1", int(sys.argv[1]), timeout_s=600)
    counts: dict[str, int] = {}
    while client.closed is None:
        client.poll(0.2)
        client.subscribe_all()
        for topic, msgs in client.messages.items():
            counts[topic] = counts.get(topic, 0) + len(msgs)
        client.messages.clear()
    print(json.dumps(counts))


if __name__ == "__main__":
    main()
