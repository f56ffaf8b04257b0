"""Checksums of stored files: recorded when a file is written, verified when it is read.

Every file a job leaves on disk (the artefact's weights and JSON, the baked fast path, the
UI preview) carries a SHA-256 that its reader checks before using a byte of it, so a file
that was truncated, bit-flipped or replaced is refused with an error naming it instead of
answering with garbage. A JSON document carries the hash of its own canonical form (sorted
keys, no whitespace, the hash key left out), so it needs no sidecar file.
"""
from __future__ import annotations

import hashlib
import json

DOCUMENT_HASH_KEY = "document_sha256"


class IntegrityError(ValueError):
    """A stored file does not match the checksum recorded when it was written."""


def sha256_bytes(data: bytes | memoryview) -> str:
    return hashlib.sha256(data).hexdigest()


def _canonical(document: dict) -> bytes:
    body = {k: v for k, v in document.items() if k != DOCUMENT_HASH_KEY}
    return json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()


def seal_document(document: dict) -> dict:
    """`document` plus its own checksum under DOCUMENT_HASH_KEY (a new dict)."""
    return {**document, DOCUMENT_HASH_KEY: sha256_bytes(_canonical(document))}


def verify_document(document: dict, name: str, required: bool = True) -> None:
    """Raise IntegrityError when the document's recorded checksum does not match its content
    (or is absent and `required`: documents written before checksums existed pass otherwise)."""
    recorded = document.get(DOCUMENT_HASH_KEY)
    if recorded is None:
        if required:
            raise IntegrityError(f"{name} has no {DOCUMENT_HASH_KEY}")
        return
    try:
        actual = sha256_bytes(_canonical(document))
    except (TypeError, ValueError) as exc:
        raise IntegrityError(f"{name} cannot be canonicalised: {exc}") from None
    if recorded != actual:
        raise IntegrityError(f"{name}: checksum mismatch (the file was modified or corrupted after it was written)")
