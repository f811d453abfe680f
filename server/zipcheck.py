"""Checks of an uploaded zip (a rig bundle or a USD package) before anything is unpacked: each
problem is an :class:`~server.assets.UploadError` (HTTP 422) naming the entry and what is
wrong, instead of an exception from :mod:`zipfile` deep in the import.

Refused: an unreadable archive, the same name twice, a file that is also a folder of another
entry (``a`` and ``a/b``), encrypted entries, compression methods other than store, deflate,
bzip2 and lzma, a central directory that disagrees with an entry's local header (sizes, name),
a stored entry whose sizes differ, and data that does not match its CRC-32. The data check
streams each entry (1 MiB at a time, never more than the sizes the directory declares, whose
sum the caller bounds), so it needs little memory.
"""

from __future__ import annotations

import struct
import zipfile
from pathlib import Path, PurePosixPath

from .assets import UploadError

SUPPORTED_METHODS = {zipfile.ZIP_STORED: "store", zipfile.ZIP_DEFLATED: "deflate", zipfile.ZIP_BZIP2: "bzip2",
                     zipfile.ZIP_LZMA: "lzma"}
_LOCAL = struct.Struct("<4s5H3L2H")  # signature, version, flags, method, time, date, crc, sizes, name/extra lengths


def check_zip(path: Path, what: str = "the rig zip", max_bytes: int | None = None) -> None:
    """Raise :class:`UploadError` naming the first problem of the zip at ``path``."""
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as err:
        raise UploadError(f"{what} is not a readable zip archive ({err})") from None
    with zf, open(path, "rb") as raw:
        members = zf.infolist()
        if max_bytes is not None and sum(m.file_size for m in members) > max_bytes:
            raise UploadError(f"{what} unpacks to more than {max_bytes} bytes")
        names, files = set(), set()
        for m in members:
            name = m.filename.rstrip("/")
            if name in names:
                raise UploadError(f"{what} names {name!r} twice")
            names.add(name)
            if not m.is_dir():
                files.add(name)
        for m in members:
            parts = PurePosixPath(m.filename).parts
            for i in range(1, len(parts)):
                prefix = "/".join(parts[:i])
                if prefix in files:
                    raise UploadError(f"{what} has a file {prefix!r} and an entry {m.filename!r} inside it as if "
                                      f"it were a folder")
        for m in members:
            _check_header(raw, m, what)
        for m in members:
            if not m.is_dir():
                _check_data(zf, m, what)


def _check_header(raw, m: zipfile.ZipInfo, what: str) -> None:
    name = repr(m.filename)
    if m.flag_bits & 0x1:
        raise UploadError(f"{what}: entry {name} is encrypted (encrypted zips are not supported)")
    if m.compress_type not in SUPPORTED_METHODS:
        raise UploadError(f"{what}: entry {name} uses compression method {m.compress_type}, which is not supported "
                          f"(use {', '.join(SUPPORTED_METHODS.values())})")
    if m.compress_type == zipfile.ZIP_STORED and m.compress_size != m.file_size:
        raise UploadError(f"{what}: entry {name} is stored uncompressed but the central directory gives it "
                          f"{m.compress_size} bytes stored and {m.file_size} bytes unpacked")
    raw.seek(m.header_offset)
    head = raw.read(_LOCAL.size)
    if len(head) != _LOCAL.size:
        raise UploadError(f"{what}: entry {name}'s local header is cut off")
    sig, _, flags, method, _, _, crc, csize, usize, nlen, _ = _LOCAL.unpack(head)
    if sig != b"PK\x03\x04":
        raise UploadError(f"{what}: entry {name} has no local header where the central directory points")
    local_name = raw.read(nlen)
    if local_name.decode("utf-8" if flags & 0x800 else "cp437", "replace") != m.orig_filename:
        raise UploadError(f"{what}: entry {name} is named differently in its local header")
    if method != m.compress_type or flags & 0x1 != m.flag_bits & 0x1:
        raise UploadError(f"{what}: entry {name}'s local header and the central directory disagree on its "
                          f"compression or encryption")
    if not flags & 0x8 and (csize, usize) != (m.compress_size, m.file_size) and 0xFFFFFFFF not in (csize, usize):
        raise UploadError(f"{what}: entry {name}: the central directory gives {m.file_size} bytes unpacked "
                          f"({m.compress_size} stored), its local header {usize} ({csize})")


def _check_data(zf: zipfile.ZipFile, m: zipfile.ZipInfo, what: str) -> None:
    try:
        with zf.open(m) as src:
            while src.read(1 << 20):
                pass
    except zipfile.BadZipFile as err:
        problem = "bad CRC-32" if "CRC" in str(err) else str(err)
        raise UploadError(f"{what}: entry {m.filename!r} is damaged ({problem}: its data does not match the "
                          "central directory)") from None
    except (EOFError, OSError, ValueError, NotImplementedError, RuntimeError) as err:
        raise UploadError(f"{what}: entry {m.filename!r} cannot be read ({type(err).__name__}: {err})") from None
