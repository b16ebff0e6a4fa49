"""The file's own checksum: a damaged copy of a model is refused, not run.

An exported file carries the metadata key ``sha256``: the SHA-256 (64 lower-case hex digits)
of the file's bytes with that value written as 64 ``0`` characters. A copy with flipped or
missing bytes in its weights still loads in onnxruntime and gives other labels; its bytes no
longer give the recorded digest, so ``tactile-check`` and ``tactile-run`` refuse it.

The value is found in the serialized file as its metadata entry, key ``sha256`` (protobuf field
1, 6 bytes) then a 64-byte value (field 2): ``0a 06 "sha256" 12 40``. Standard library only (the
runtime checks files on a board).
"""

from __future__ import annotations

import hashlib
import re

from tactile.errors import ModelContractError

KEY = "sha256"
PLACEHOLDER = "0" * 64
"""The value written while the file is hashed (:func:`seal`)."""
_ENTRY = b"\x0a\x06" + KEY.encode() + b"\x12\x40"
_HEX = re.compile(r"[0-9a-f]{64}")


def _value_at(data: bytes) -> int:
    """Where the ``sha256`` entry's value starts in ``data``; ModelContractError unless the
    entry is there exactly once."""
    n = data.count(_ENTRY)
    if n != 1:
        where = "not in the file's bytes" if n == 0 else f"in the file's bytes {n} times"
        raise ModelContractError(f"metadata key {KEY!r}: its entry is {where} (once expected)")
    return data.index(_ENTRY) + len(_ENTRY)


def digest(data: bytes) -> str:
    """The SHA-256 of ``data`` (a serialized model) with its ``sha256`` value read as
    :data:`PLACEHOLDER`."""
    at = _value_at(data)
    view = memoryview(data)  # the file hashed in place, not copied
    h = hashlib.sha256(view[:at])
    h.update(PLACEHOLDER.encode())
    h.update(view[at + 64:])
    return h.hexdigest()


def seal(data: bytes) -> bytes:
    """``data``, a serialized model whose ``sha256`` metadata value is :data:`PLACEHOLDER`,
    with that value replaced by the file's digest (:func:`digest`)."""
    at = _value_at(data)
    if data[at:at + 64] != PLACEHOLDER.encode():
        raise ValueError(f"the {KEY!r} value is not the placeholder")
    return data[:at] + digest(data).encode() + data[at + 64:]


def verify(data: bytes, meta: dict) -> bool:
    """True when ``meta`` (the file's metadata) records a ``sha256`` and ``data`` (the file's
    bytes) gives it; False when it records none (a file exported before checksums, or one
    whose key was removed after an edit). :class:`ModelContractError` when the bytes give
    another digest: the file was damaged or changed after export."""
    recorded = meta.get(KEY)
    if recorded is None:
        return False
    if not isinstance(recorded, str) or not _HEX.fullmatch(recorded):
        raise ModelContractError(f"metadata key {KEY!r} is {str(recorded)[:70]!r}: not 64 "
                                 "lower-case hex digits")
    try:
        found = digest(data)
    except ModelContractError as e:
        raise ModelContractError(f"damaged: {e}") from None
    if found != recorded:
        raise ModelContractError(
            f"damaged: the file's bytes give sha256 {found[:12]}..., its metadata records "
            f"{recorded[:12]}... (changed or cut since export): copy it again, or export it "
            f"again; after editing a file on purpose, remove its {KEY!r} key")
    return True


__all__ = ["KEY", "PLACEHOLDER", "digest", "seal", "verify"]
