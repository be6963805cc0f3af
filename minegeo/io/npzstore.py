"""minegeo's own ``.npz`` stores (prepared maps, intersection bases), read without trusting them.

A store is an uncompressed NumPy ``.npz`` archive: one ``.npy`` member per array plus a 0-d
unicode ``meta`` member holding JSON (format, version, parameters, provenance, integrity record).
These helpers are shared by every store so that each is read, checked and hashed the same way:

* :func:`open_store`: the path must be a regular file that starts with the ZIP signature, so a
  stream (``/dev/zero``), a folder, an empty file, a single ``.npy`` array or random bytes are
  refused with one sentence naming what the file should have been, before NumPy reads it (NumPy's
  own message for such a file advises loading it with ``allow_pickle``, which a minegeo store never
  needs and a user must not be told to do);
* :func:`member_header`: a member must be stored uncompressed and hold exactly the bytes its
  ``.npy`` header announces (so a member cannot make the reader allocate more than the file
  holds), and hold no Python objects;
* :func:`array_digest` and :func:`json_digest`: the SHA-256 of an array (dtype with byte order,
  shape, bytes in C order) and of a JSON value (canonical: sorted keys, no spaces, ASCII), the
  bricks of every store's integrity record.
"""

from __future__ import annotations

import errno
import hashlib
import json
import math
import os
import stat
import zipfile
from pathlib import Path

import numpy as np

from minegeo.errors import FileFormatError

__all__ = ["open_store", "member_header", "array_digest", "json_digest", "crc_failure"]

#: first bytes of a ZIP archive (a local file header; an archive without members starts with the
#: end-of-central-directory record)
_ZIP_SIGNATURES = (b"PK\x03\x04", b"PK\x05\x06")
_NPY_SIGNATURE = b"\x93NUMPY"


def open_store(path, what: str) -> np.lib.npyio.NpzFile:
    """Open the ``.npz`` store ``path`` (an open :class:`numpy.lib.npyio.NpzFile`, to be closed by
    the caller), after checking that it is a regular file holding a ZIP archive.

    Parameters
    ----------
    path : str or Path
    what : str
        What the file should be, for the messages (e.g. ``"minegeo prepared map"``).

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    FileFormatError
        A folder, a stream or device, an empty file, a single NumPy array, anything that is not a
        ZIP archive, or a damaged archive: ``"<path>: not a <what> (<why>)"``.
    """
    p = Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        raise FileNotFoundError(errno.ENOENT, "No such file or directory", str(p)) from None
    except OSError as exc:
        raise FileFormatError(p, f"cannot read it ({exc.strerror or exc})") from None
    if stat.S_ISDIR(st.st_mode):
        raise FileFormatError(p, f"is a folder, not a {what}")
    if not stat.S_ISREG(st.st_mode):
        raise FileFormatError(p, f"not a {what} (not a regular file: a device, stream or socket)")
    try:
        with open(p, "rb") as fh:
            head = fh.read(8)
    except OSError as exc:
        raise FileFormatError(p, f"cannot read it ({exc.strerror or exc})") from None
    if not head:
        raise FileFormatError(p, f"not a {what} (empty file)")
    if head.startswith(_NPY_SIGNATURE):
        raise FileFormatError(p, f"not a {what} (a single NumPy array .npy, not an .npz archive)")
    if head[:4] not in _ZIP_SIGNATURES:
        raise FileFormatError(p, f"not a {what} (not a NumPy .npz archive)")
    try:
        z = np.load(p, allow_pickle=False)
    except (OSError, ValueError, EOFError, RuntimeError, zipfile.BadZipFile) as exc:
        raise FileFormatError(p, f"not a {what} (damaged .npz archive: {str(exc)[:200]})") from None
    if not isinstance(z, np.lib.npyio.NpzFile):  # not reachable after the signature check; kept as a guard
        raise FileFormatError(p, f"not a {what} (not a NumPy .npz archive)")
    return z


def member_header(zf: zipfile.ZipFile, info: zipfile.ZipInfo):
    """``(problem, shape, dtype)`` of one ``.npy`` member of an archive; ``problem`` is None when
    the member is stored uncompressed and holds exactly the bytes its header announces."""
    if not info.filename.endswith(".npy"):
        return "not a NumPy array", None, None
    if info.compress_type != zipfile.ZIP_STORED or info.compress_size != info.file_size:
        return "compressed (minegeo writes its stores uncompressed)", None, None
    try:
        with zf.open(info) as fp:
            version = np.lib.format.read_magic(fp)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(fp)
            elif version == (2, 0):
                shape, _, dtype = np.lib.format.read_array_header_2_0(fp)
            else:
                return f"NumPy format version {version} is not supported", None, None
            header = fp.tell()
    except (ValueError, OSError, EOFError, RuntimeError, zipfile.BadZipFile) as exc:
        return f"unreadable array header ({exc})", None, None
    if dtype.hasobject:
        return "holds Python objects", None, None
    nbytes = math.prod(shape) * dtype.itemsize
    if header + nbytes != info.file_size:
        return f"its header announces {nbytes} bytes but it holds {info.file_size - header}", None, None
    return None, shape, dtype


def array_digest(a: np.ndarray) -> str:
    """SHA-256 (hex) of one stored array: its dtype (with byte order), its shape and its bytes
    in C order."""
    a = np.ascontiguousarray(a)
    h = hashlib.sha256(f"{a.dtype.str}|{json.dumps(list(a.shape))}|".encode("ascii"))
    try:
        h.update(a.reshape(-1).view(np.uint8))
    except (ValueError, TypeError):  # a dtype without a byte view (not one minegeo writes)
        h.update(a.tobytes())
    return h.hexdigest()


def json_digest(obj) -> str:
    """SHA-256 (hex) of the canonical JSON of ``obj`` (sorted keys, no spaces, ASCII)."""
    blob = json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(blob.encode("ascii")).hexdigest()


def crc_failure(exc: BaseException) -> str | None:
    """The member named by a ZIP checksum failure (``zipfile.BadZipFile: Bad CRC-32 for file 'x'``,
    raised on reading a member whose bytes changed after the archive was written), else None."""
    text = str(exc)
    prefix = "Bad CRC-32 for file"
    if isinstance(exc, zipfile.BadZipFile) and text.startswith(prefix):
        return text[len(prefix):].strip()[:80]
    return None
