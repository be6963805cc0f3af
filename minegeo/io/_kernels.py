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
    while ip < n:
        # a back reference needs 3 bytes to hash and match; the last two bytes are literals
        ref = -1
        off = 0
        if ip + 2 < n:
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
    if lit > 0:
        out[op - lit - 1] = lit - 1
    else:
        op -= 1
    return op


# ----------------------------------------------------------------------------- text parsing

#: 10^0 .. 10^22: every one is exactly representable in float64 (5^22 < 2^53)
POW10 = np.array([10.0**k for k in range(23)])
_TWO53 = 1 << 53


@njit
def _is_space(c):
    return c == 32 or c == 9 or c == 13


@njit
def _digit_run(buf, j, end, m, nd):
    """Consume the decimal digits of ``buf[j:end]`` into the mantissa ``m`` (leading zeros are not
    significant; ``nd`` counts the significant digits). Returns ``(j, m, nd, digits read)``, with
    ``nd = -1`` when a 19th significant digit would overflow the int64 mantissa."""
    count = 0
    while j < end and buf[j] >= 48 and buf[j] <= 57:
        d = np.int64(buf[j] - 48)
        if m != 0 or d != 0:
            if nd >= 18:
                return j, m, -1, count
            m = m * 10 + d
            nd += 1
        count += 1
        j += 1
    return j, m, nd, count


@njit
def parse_text_kernel(buf, ncols, delim, comment, max_rows, pow10, out):
    """Fast exact parser of a numeric text table (Clinger's fast path), or a request to fall back.

    Every token must be ``[+-]digits[.digits][(e|E)[+-]digits]`` whose decimal significand
    ``m`` (leading zeros dropped) is ``<= 2^53`` and whose decimal exponent ``q`` is within
    ``[-22, 22]``. Then ``m`` and ``10^|q|`` are exact float64 numbers and one IEEE
    multiplication or division gives the correctly rounded value -- the same bits as
    ``strtod`` (Clinger 1990, "How to read floating point numbers accurately", Sec. 3).
    Anything else (more digits, ``nan``, ``inf``, other characters, a wrong number of
    columns, an empty field) returns ``status = 1`` and the caller uses NumPy's parser,
    which also produces the error messages.

    Parameters
    ----------
    buf : uint8[:]
        The text.
    ncols : int
        Values per data line.
    delim : int
        Separator byte (44 ``,`` or 59 ``;``), or 0 for whitespace only.
    comment : int
        Byte starting a comment line (35 ``#``), or -1.
    max_rows : int
        Stop after this many rows (-1: read all).
    out : float64[:, ncols]
        Preallocated output with at least as many rows as data lines.

    Returns
    -------
    (rows, status)
    """
    n = buf.shape[0]
    pos = 0
    row = 0
    while pos < n:
        if max_rows >= 0 and row >= max_rows:
            break
        end = pos
        while end < n and buf[end] != 10:
            end += 1
        j = pos
        while j < end and _is_space(buf[j]):
            j += 1
        if j == end or (comment >= 0 and buf[j] == comment):
            pos = end + 1
            continue
        if row >= out.shape[0]:
            return row, 1
        col = 0
        while j < end:
            if col >= ncols:
                return row, 1
            neg = False
            if buf[j] == 45:
                neg = True
                j += 1
            elif buf[j] == 43:
                j += 1
            j, m, nd, n_int = _digit_run(buf, j, end, np.int64(0), 0)
            if nd < 0:
                return row, 1
            frac = 0
            if j < end and buf[j] == 46:
                j, m, nd, frac = _digit_run(buf, j + 1, end, m, nd)
                if nd < 0:
                    return row, 1
            if n_int == 0 and frac == 0:
                return row, 1
            e = 0
            if j < end and (buf[j] == 101 or buf[j] == 69):
                j += 1
                eneg = False
                if j < end and buf[j] == 45:
                    eneg = True
                    j += 1
                elif j < end and buf[j] == 43:
                    j += 1
                has = False
                while j < end and buf[j] >= 48 and buf[j] <= 57:
                    has = True
                    if e < 100000:
                        e = e * 10 + (buf[j] - 48)
                    j += 1
                if not has:
                    return row, 1
                if eneg:
                    e = -e
            q = e - frac
            if m == 0:
                v = 0.0
            elif m > _TWO53 or q < -22 or q > 22:
                return row, 1
            elif q >= 0:
                v = np.float64(m) * pow10[q]
            else:
                v = np.float64(m) / pow10[-q]
            out[row, col] = -v if neg else v
            col += 1
            k = j
            while k < end and _is_space(buf[k]):
                k += 1
            if delim > 0 and k < end and buf[k] == delim:
                k += 1
                while k < end and _is_space(buf[k]):
                    k += 1
                if k == end:
                    return row, 1  # trailing separator: empty field
            elif k == j and k < end:
                return row, 1  # a character glued to the number
            j = k
        if col != ncols:
            return row, 1
        row += 1
        pos = end + 1
    return row, 0
