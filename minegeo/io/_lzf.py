"""LZF compression (PCD ``binary_compressed``), implemented in :mod:`minegeo.io._kernels`."""

from __future__ import annotations

import numpy as np

from minegeo.errors import InputError
from minegeo.io._kernels import lzf_compress_kernel, lzf_decompress_kernel

__all__ = ["lzf_compress", "lzf_decompress"]


def lzf_compress(data: bytes) -> bytes:
    """Compress ``data`` with LZF (liblzf-compatible stream, no header).

    Parameters
    ----------
    data : bytes-like

    Returns
    -------
    bytes
        The compressed stream; at most ``len(data) + len(data) // 32 + 1`` bytes.
    """
    src = np.frombuffer(memoryview(data), dtype=np.uint8)
    out = np.empty(src.size + src.size // 32 + 16, dtype=np.uint8)
    n = lzf_compress_kernel(np.ascontiguousarray(src), out)
    return out[:n].tobytes()


def lzf_decompress(data: bytes, size: int) -> bytes:
    """Decompress an LZF stream whose uncompressed length is ``size`` bytes.

    Raises
    ------
    InputError
        If the stream is corrupt or does not decompress to exactly ``size`` bytes.
    """
    src = np.ascontiguousarray(np.frombuffer(memoryview(data), dtype=np.uint8))
    out = np.empty(int(size), dtype=np.uint8)
    n = lzf_decompress_kernel(src, out)
    if n == -1:
        raise InputError(f"LZF data decompress to more than the declared {size} bytes")
    if n == -2:
        raise InputError("LZF data are corrupt or truncated")
    if n != size:
        raise InputError(f"LZF data decompress to {n} bytes, the header declares {size}")
    return out.tobytes()
