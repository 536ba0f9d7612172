"""What the first bytes of a cut compressed block still hold (MCAP and ROS 1 chunks cut by the end of a file)."""

from __future__ import annotations

import bz2

#: MCAP opcodes (spec: Records) by name, for saying which record a file ends inside
MCAP_RECORDS = {0x01: "header", 0x02: "footer", 0x03: "schema", 0x04: "channel", 0x05: "message", 0x06: "chunk",
                0x07: "message index", 0x08: "chunk index", 0x09: "attachment", 0x0A: "attachment index",
                0x0B: "statistics", 0x0C: "metadata", 0x0D: "metadata index", 0x0E: "summary offset",
                0x0F: "data end"}


def decompress_prefix(data: bytes, compression: str) -> bytes:
    """As much decompressed data as the first bytes of a compressed stream hold (b"" when nothing decodes)."""
    try:
        if compression in ("", "none"):
            return data
        if compression == "zstd":
            import zstandard

            return bytes(zstandard.ZstdDecompressor().decompressobj().decompress(data))
        if compression == "lz4":
            import lz4.frame

            return bytes(lz4.frame.LZ4FrameDecompressor().decompress(data))
        if compression == "bz2":
            return bz2.BZ2Decompressor().decompress(data)
    except Exception:  # noqa: BLE001 - the codecs raise their own errors on damaged input: nothing to recover
        return b""
    return b""
