"""Malformed rig zips answer a 4xx JSON error naming the problem (issue 16, Build 6).

Finding covered (main at 328eb67): "13 malformed inputs answer a plain-text 500: rig zips with
a file `a` and a file `a/b`, the encrypted flag, compression method 99, a flipped data byte
(bad CRC), a central directory understating file_size" (the five zip cases; the clip cases are
in test_limits.py). Every zip is built here, from a tiny valid URDF bundle.
"""

from __future__ import annotations

import io
import struct
import zipfile

import pytest

from dcc_client.client import ServiceError

URDF = b'<robot name="r"><link name="base"/></robot>\n'
PAYLOAD = b"solid t\nendsolid t\n" * 40  # a stored entry whose bytes the tests damage


def _zip(entries, method=zipfile.ZIP_STORED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", method) as zf:
        for name, data in entries:
            zf.writestr(name, data)
    return buf.getvalue()


def _central(data: bytes, name: bytes) -> int:
    """Offset of the central directory header of entry ``name``."""
    at = data.index(b"PK\x01\x02")
    while True:
        nlen = struct.unpack_from("<H", data, at + 28)[0]
        if data[at + 46:at + 46 + nlen] == name:
            return at
        at = data.index(b"PK\x01\x02", at + 4)


def _local(data: bytes, name: bytes) -> int:
    return struct.unpack_from("<L", data, _central(data, name) + 42)[0]


def file_and_folder() -> bytes:
    return _zip([("hand.urdf", URDF), ("a", b"x"), ("a/b", b"y")])


def encrypted_flag() -> bytes:
    data = bytearray(_zip([("hand.urdf", URDF), ("mesh.stl", PAYLOAD)]))
    for at, flag in ((_local(data, b"mesh.stl"), 6), (_central(data, b"mesh.stl"), 8)):
        struct.pack_into("<H", data, at + flag, struct.unpack_from("<H", data, at + flag)[0] | 0x1)
    return bytes(data)


def method_99() -> bytes:
    data = bytearray(_zip([("hand.urdf", URDF), ("mesh.stl", PAYLOAD)]))
    struct.pack_into("<H", data, _local(data, b"mesh.stl") + 8, 99)
    struct.pack_into("<H", data, _central(data, b"mesh.stl") + 10, 99)
    return bytes(data)


def bad_crc() -> bytes:
    data = bytearray(_zip([("hand.urdf", URDF), ("mesh.stl", PAYLOAD)]))
    start = _local(data, b"mesh.stl") + 30 + len(b"mesh.stl")
    data[start + 10] ^= 0x20  # one flipped data byte
    return bytes(data)


def understated_size() -> bytes:
    data = bytearray(_zip([("hand.urdf", URDF), ("mesh.stl", PAYLOAD)], zipfile.ZIP_DEFLATED))
    struct.pack_into("<L", data, _central(data, b"mesh.stl") + 24, 10)  # file_size: 10 bytes, not 760
    return bytes(data)


CASES = {  # case -> (hostile zip, words the error must contain)
    "file a and file a/b": (file_and_folder, ("'a'", "'a/b'")),
    "encrypted flag": (encrypted_flag, ("mesh.stl", "encrypted")),
    "compression method 99": (method_99, ("mesh.stl", "compression method 99")),
    "bad CRC": (bad_crc, ("mesh.stl", "CRC")),
    "central directory understating file_size": (understated_size, ("mesh.stl", "central directory", "10 bytes")),
}


@pytest.fixture(scope="module")
def vic(service):
    return service.client("vic")


@pytest.mark.parametrize("case", list(CASES))
def test_malformed_rig_zip_is_a_422_naming_the_problem(vic, service, case):
    build, words = CASES[case]
    with pytest.raises(ServiceError) as err:
        vic.upload_bytes("rig", build(), "hand.zip")
    assert err.value.status == 422, (err.value.status, err.value.detail)
    detail = err.value.detail
    assert detail.startswith("not a valid rig:") and all(w in detail for w in words), detail
    assert str(service.data_dir) not in detail and "/tmp" not in detail
    assert not list((service.data_dir / "tmp").iterdir())  # nothing of the upload left behind
