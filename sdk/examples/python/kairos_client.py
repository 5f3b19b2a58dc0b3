#!/usr/bin/env python3
"""A minimal Kairos protocol v1 client in Python, written from docs/PROTOCOL.md alone.

It connects over QUIC (aioquic), pins the server certificate, sends Hello, runs ROUNDS rounds of
one task (answering FetchObservation on the round's stream), ends the task, and prints one line per
round. It exists to show the protocol document is sufficient, and is exercised against the Rust
responder by `cargo test -p kairos-sdk --test it python_client:: -- --ignored`.

    pip install aioquic msgpack numpy
    python kairos_client.py HOST:PORT sha256:<64 hex> TOKEN [ROUNDS]
"""

import asyncio
import hashlib
import ssl
import struct
import sys
import time

import msgpack
import numpy as np
from aioquic.asyncio import connect
from aioquic.quic.configuration import QuicConfiguration
from cryptography.hazmat.primitives.serialization import Encoding

KIND = {"Hello": 0x01, "Welcome": 0x02, "Submit": 0x10, "FetchObservation": 0x11,
        "FreshObservation": 0x12, "Reply": 0x13, "EndTask": 0x20, "TaskEnded": 0x21,
        "Error": 0x7F}
NAME = {v: k for k, v in KIND.items()}
CLOCK_ORIGIN = time.monotonic_ns()


def now_us() -> int:
    """The client clock: monotonic µs from an arbitrary origin (PROTOCOL.md §10)."""
    return (time.monotonic_ns() - CLOCK_ORIGIN) // 1000


def frame(kind: str, body: dict) -> bytes:
    payload = msgpack.packb(body, use_bin_type=True)
    return struct.pack(">BI", KIND[kind], len(payload)) + payload


async def read_message(reader: asyncio.StreamReader, max_frame: int = 16 << 20):
    """One frame from a stream: (kind name, body), or None at a clean end of stream."""
    try:
        header = await reader.readexactly(5)
    except asyncio.IncompleteReadError as error:
        if not error.partial:
            return None
        raise ValueError("truncated frame header") from error
    kind, length = struct.unpack(">BI", header)
    if kind not in NAME:
        raise ValueError(f"unknown frame kind 0x{kind:02x}")
    if length > max_frame:
        raise ValueError(f"frame of {length} bytes exceeds {max_frame}")
    body = msgpack.unpackb(await reader.readexactly(length), raw=False)
    return NAME[kind], body


def tensor(array: np.ndarray) -> dict:
    dtype = {"float32": "f32", "float16": "f16", "uint8": "u8"}[str(array.dtype)]
    little = np.ascontiguousarray(array.astype(array.dtype.newbyteorder("<"), copy=False))
    return {"dtype": dtype, "shape": list(array.shape), "data": little.tobytes()}


def observation(state_dim: int, step: int) -> dict:
    image = np.full((8, 8, 3), step % 256, dtype=np.uint8)
    return {
        "captured_at_us": now_us(),
        "state": tensor(np.linspace(0, 1, state_dim, dtype=np.float32)),
        "images": [{"camera": "front", "payload": {"encoding": "raw", "tensor": tensor(image)}}],
        "instruction": "pick up the cube",
    }


def finish(writer) -> None:
    """Finishes our send side, unless the server already stopped it (it may, after an Error:
    PROTOCOL.md §7); then there is nothing left to finish."""
    try:
        writer.write_eof()
    except RuntimeError:
        pass


async def request(client, messages, handle=None, finish_after=False):
    """Opens a stream, sends `messages` (then finishes the send side if `finish_after`), and reads
    until a final answer; `handle(kind, body)` yields the answers to anything else."""
    reader, writer = await client.create_stream()
    for kind, body in messages:
        writer.write(frame(kind, body))
    if finish_after:
        finish(writer)
    while True:
        message = await read_message(reader)
        if message is None:
            raise ConnectionError("stream ended without an answer")
        kind, body = message
        if kind in ("Welcome", "Reply", "TaskEnded", "Error"):
            return kind, body, writer
        if handle is None:
            raise ValueError(f"unexpected {kind}")
        for reply in handle(kind, body):
            writer.write(frame(*reply))


async def main(address: str, pin: str, token: str, rounds: int) -> int:
    host, port = address.rsplit(":", 1)
    configuration = QuicConfiguration(
        is_client=True, alpn_protocols=["kairos/1"], server_name="kairos",
        # The pin replaces the chain check; the handshake signature is still verified.
        verify_mode=ssl.CERT_NONE,
    )
    async with connect(host, int(port), configuration=configuration) as client:
        certificate = client._quic.tls._peer_certificate  # aioquic keeps the leaf here
        seen = "sha256:" + hashlib.sha256(certificate.public_bytes(Encoding.DER)).hexdigest()
        expected = pin.lower() if pin.startswith("sha256:") else "sha256:" + pin.lower()
        if seen != expected:
            print(f"certificate {seen} is not the pinned {expected}", file=sys.stderr)
            return 2

        kind, welcome, _ = await request(client, [("Hello", {
            "protocol": 1, "token": token, "client": "kairos-python-example/1"})], finish_after=True)
        if kind != "Welcome":
            print(f"refused: {welcome['code']}: {welcome['message']}", file=sys.stderr)
            return 3
        model = welcome["model"]
        print(f"welcome from {welcome['server']} as {welcome['robot']}: model {model['name']}")

        task = int.from_bytes(np.random.bytes(8), "little")
        last_exec = None
        for round_id in range(rounds):
            # Capture first: an observation cannot be captured after the message carrying it
            # was sent, and the server checks that.
            captured = observation(model["state_dim"], round_id)
            submit = {"task": task, "round": round_id, "sent_at_us": now_us(),
                      "observation": captured}
            if last_exec is not None:
                submit["last_exec"] = last_exec
            refetches = []

            def on_fetch(kind, body):
                refetches.append(body["age_us"])
                fresh = observation(model["state_dim"], round_id)
                yield "FreshObservation", {"sent_at_us": now_us(), "observation": fresh}

            kind, answer, writer = await request(client, [("Submit", submit)], on_fetch)
            finish(writer)
            if kind == "Error":
                print(f"round {round_id}: {answer['code']}: {answer['message']}", file=sys.stderr)
                return 4
            actions = answer["actions"]
            values = np.frombuffer(actions["data"], dtype="<f4").reshape(actions["shape"])
            timing = answer["timing"]
            print(f"round {answer['round']}: H={answer['horizon']} of N={answer['chunk_len']} "
                  f"actions{list(values.shape)} policy={answer['policy']} "
                  f"total={timing['total_us']}us refetches={len(refetches)}")
            # Pretend the chunk executed instantly: nothing remains of it.
            last_exec = {"exec_started_at_us": now_us(), "actions_remaining": 0,
                         "control_hz": 30.0}

        kind, ended, _ = await request(client, [("EndTask", {
            "task": task, "outcome": "done", "sent_at_us": now_us(), "last_exec": last_exec})],
            finish_after=True)
        if kind != "TaskEnded":
            print(f"EndTask refused: {ended['code']}", file=sys.stderr)
            return 5
        print(f"task ended: {ended['rounds']} rounds")
    return 0


if __name__ == "__main__":
    if len(sys.argv) < 4:
        print(__doc__, file=sys.stderr)
        sys.exit(1)
    sys.exit(asyncio.run(main(sys.argv[1], sys.argv[2], sys.argv[3],
                              int(sys.argv[4]) if len(sys.argv) > 4 else 3)))
