"""The MCAP record layout both the end-of-file repair (:mod:`.mcap_end`) and the damage check
(:mod:`.damage`) read: opcodes and the fixed heads of the records they parse (MCAP spec,
little endian)."""

from __future__ import annotations

import struct

OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE = 0x01, 0x02, 0x03, 0x04, 0x05
OP_CHUNK, OP_MESSAGE_INDEX, OP_DATA_END = 0x06, 0x07, 0x0F
#: Every record: opcode, length of the content that follows.
RECORD = struct.Struct("<BQ")
#: A message record's head: channel, sequence, log time.
MESSAGE_HEAD = struct.Struct("<HIQ")
