"""Pure-Python LZF decoder (liblzf ``lzf_d.c`` semantics), the naive twin of the Numba kernel."""

from __future__ import annotations


def naive_lzf_decompress(src: bytes) -> bytes:
    """Decode an LZF stream chunk by chunk; raises ValueError on a corrupt stream."""
    out = bytearray()
    i = 0
    while i < len(src):
        ctrl = src[i]
        i += 1
        if ctrl < 32:  # literal run of ctrl + 1 bytes
            run = src[i : i + ctrl + 1]
            if len(run) != ctrl + 1:
                raise ValueError("truncated literal run")
            out += run
            i += ctrl + 1
        else:  # back reference
            length = ctrl >> 5
            if length == 7:
                length += src[i]
                i += 1
            start = len(out) - ((ctrl & 0x1F) << 8) - src[i] - 1
            i += 1
            if start < 0:
                raise ValueError("reference before start")
            for k in range(length + 2):  # byte by byte: overlapping copies repeat
                out.append(out[start + k])
    return bytes(out)
