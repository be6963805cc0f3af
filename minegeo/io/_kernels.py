"""Numba kernels of :mod:`minegeo.io`: LZF compression as used by PCD ``binary_compressed``.

Contiguous ``uint8`` arrays in, no checks (the wrappers in :mod:`minegeo.io._lzf` validate).

LZF (Marc Lehmann's liblzf, ``lzf_d.c`` / ``lzf_c.c``) is a byte-oriented LZ77 variant.
The compressed stream is a sequence of chunks, each starting with a control byte ``c``:

* ``c < 32``: a literal run; the next ``c + 1`` bytes are copied to the output.
* ``c >= 32``: a back reference. ``L = c >> 5`` (if ``L == 7`` one more byte is added),
  the match length is ``L + 2`` bytes, and the source starts ``((c & 31) << 8) + b + 1``
  bytes before the current output position, ``b`` being the next byte. Source and
  destination may overlap (run-length behaviour), so copying is byte by byte.

Hence offsets are < 8192 bytes and match lengths are 3..264 bytes.
"""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit

_HLOG = 14
_MAX_OFF = 1 << 13
_MAX_REF = (1 << 8) + (1 << 3)  # 264: longest match (len - 2 <= 7 + 255)
_MAX_LIT = 1 << 5  # 32


@njit
def lzf_decompress_kernel(src, out):
    """Decompress ``src`` into the preallocated ``out``.

    Returns the number of bytes written, ``-1`` if the output buffer is too small, or
    ``-2`` if the stream is corrupt (reference before the start, truncated chunk).
    """
    ip = 0
    op = 0
    n_in = src.shape[0]
    n_out = out.shape[0]
    while ip < n_in:
        ctrl = np.int64(src[ip])
        ip += 1
        if ctrl < 32:
            ctrl += 1
            if op + ctrl > n_out:
                return -1
            if ip + ctrl > n_in:
                return -2
            for k in range(ctrl):
                out[op + k] = src[ip + k]
            op += ctrl
            ip += ctrl
        else:
            length = ctrl >> 5
            ref = op - ((ctrl & 0x1F) << 8) - 1
            if ip >= n_in:
                return -2
            if length == 7:
                length += np.int64(src[ip])
                ip += 1
                if ip >= n_in:
                    return -2
            ref -= np.int64(src[ip])
            ip += 1
            length += 2
            if op + length > n_out:
                return -1
            if ref < 0:
                return -2
            for k in range(length):
                out[op + k] = out[ref + k]
            op += length
    return op


@njit
def lzf_compress_kernel(src, out):
    """Compress ``src`` into ``out`` (size >= ``len(src) + len(src) // 32 + 16``).

    Greedy LZF encoder with a 2^14-entry hash table of 3-byte prefixes. Returns the number
    of bytes written. Output is valid LZF readable by liblzf / PCL.
    """
    n = src.shape[0]
    htab = np.full(1 << _HLOG, -1, dtype=np.int64)
    ip = 0
    op = 1  # out[0] is reserved for the length of the first literal run
    lit = 0
    while ip + 2 < n:
        v = (np.int64(src[ip]) << 16) | (np.int64(src[ip + 1]) << 8) | np.int64(src[ip + 2])
        h = ((v * 2654435761) >> (24 - _HLOG + 8)) & ((1 << _HLOG) - 1)
        ref = htab[h]
        htab[h] = ip
        off = ip - ref - 1
        if (
            ref >= 0
            and off < _MAX_OFF
            and src[ref] == src[ip]
            and src[ref + 1] == src[ip + 1]
            and src[ref + 2] == src[ip + 2]
        ):
            maxlen = n - ip
            if maxlen > _MAX_REF:
                maxlen = _MAX_REF
            length = 3
            while length < maxlen and src[ref + length] == src[ip + length]:
                length += 1
            # close the pending literal run (or drop its reserved byte)
            if lit > 0:
                out[op - lit - 1] = lit - 1
            else:
                op -= 1
            enc = length - 2
            if enc < 7:
                out[op] = (off >> 8) + (enc << 5)
                op += 1
            else:
                out[op] = (off >> 8) + (7 << 5)
                out[op + 1] = enc - 7
                op += 2
            out[op] = off & 0xFF
            op += 1
            lit = 0
            op += 1  # reserve the length byte of the next literal run
            ip += length
        else:
            out[op] = src[ip]
            op += 1
            ip += 1
            lit += 1
            if lit == _MAX_LIT:
                out[op - lit - 1] = lit - 1
                lit = 0
                op += 1
    while ip < n:
        out[op] = src[ip]
        op += 1
        ip += 1
        lit += 1
        if lit == _MAX_LIT:
            out[op - lit - 1] = lit - 1
            lit = 0
            op += 1
    if lit > 0:
        out[op - lit - 1] = lit - 1
    else:
        op -= 1
    return op
