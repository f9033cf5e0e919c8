"""Floor of the CPU fallback: raw Zenoh carrying our CDR, with none of the transport.

What any Python design of the CPU route must do per message, and nothing else: the sender
stamps a prepared ``ExperimentalTensor``, serializes it with our CDR codec into a reused buffer
and puts it with a 33-byte rmw_zenoh attachment; the receiver decodes the attachment, copies the
payload out of Zenoh (``to_bytes``, as the raw peer does), deserializes it and takes the
zero-copy NumPy view. No discovery, routing, sequence tracking, queue or executor. Beside
"Zenoh put (copy)" in the same run it prices the codec and view alone; beside "ours: CPU
fallback" it prices our transport's own bookkeeping.
"""

from __future__ import annotations

from typing import Any

import zenoh

from benchmarks.paths import PathSettings
from benchmarks.paths.zenoh_common import ZenohReceiver, declare_blocking_publisher, open_session
from benchmarks.protocol import STAMP_SIZE, stamp_into

LABEL = "floor: raw Zenoh carrying our CDR (codec + view only)"
KIND = "peer"
TOPOLOGY = "pair"

TENSOR_TYPE = "tensor_msgs/msg/ExperimentalTensor"
_GID = bytes(range(16))  # any gid: nothing looks it up


class CodecFloorSender:
    """Stamps one prepared CPU tensor message per size, serializes it and puts the bytes."""

    def __init__(self, settings: PathSettings) -> None:
        from buffer_pubsub import wire

        self._wire = wire
        self._session = open_session(settings, listen=False, shared_memory=False)
        self._publisher = declare_blocking_publisher(self._session, settings)
        self._msg: Any = None
        self._view: Any = None
        self._out: bytearray | None = None

    def prepare(self, nbytes: int) -> None:
        """The user's message, made untimed (as our CPU fallback path does)."""
        import numpy as np

        import tensor_conversions.numpy as tc

        self._msg = tc.allocate_tensor_msg((nbytes,), np.uint8, backend="cpu")
        self._view = tc.from_output_tensor_msg(self._msg)[:STAMP_SIZE]
        self._out = None

    def send(self, seq: int) -> None:
        """Stamp, serialize into the reused buffer, put with an attachment."""
        from rosidl_buffer.messages import serialize_message

        stamp_into(self._view, seq)
        self._out = serialize_message(self._msg, out=self._out)
        attachment = self._wire.Attachment(seq, 0, _GID).encode()
        self._publisher.put(self._out, attachment=attachment)

    def close(self) -> None:
        """Undeclare and close."""
        self._publisher.undeclare()
        self._session.close()


def make_sender(settings: PathSettings, shared: Any) -> CodecFloorSender:
    """The publishing side."""
    return CodecFloorSender(settings)


def make_receiver(settings: PathSettings, shared: Any) -> ZenohReceiver:
    """The subscribing side: attachment, ``to_bytes``, deserialize, zero-copy view."""
    from buffer_pubsub import wire
    from rosidl_buffer.messages import deserialize_message, get_message_type
    import tensor_conversions.numpy as tc

    msg_type = get_message_type(TENSOR_TYPE)

    def read(sample: zenoh.Sample) -> memoryview:
        wire.Attachment.decode(sample.attachment.to_bytes())
        msg = deserialize_message(sample.payload.to_bytes(), msg_type)
        return memoryview(tc.from_input_tensor_msg(msg, clone=False)[:STAMP_SIZE])

    return ZenohReceiver(settings, shared_memory=False, read=read)
