"""API keys as stored: ``ctk_<key_id>_<secret>``, only ``sha256(secret)`` kept.

``key_id`` (12 hex digits) finds the stored row; the secret (32 random bytes, URL-safe base64) is
never stored, only its hash, compared in constant time. Roles are ordered
``viewer < fleet < admin``. Presenting and checking a key over HTTP is :mod:`cranetwin.api.auth`.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from typing import Literal

Role = Literal["viewer", "fleet", "admin"]
ROLES: tuple[Role, ...] = ("viewer", "fleet", "admin")
KEY_PREFIX = "ctk_"


def hash_secret(secret: str) -> str:
    """Hex sha256 of a key's secret part (what is stored)."""
    return hashlib.sha256(secret.encode("utf-8")).hexdigest()


def new_key() -> tuple[str, str, str]:
    """A fresh key: ``(key_id, token, secret_hash)``; the token is shown to the user once."""
    key_id = secrets.token_hex(6)
    secret = secrets.token_urlsafe(32)
    return key_id, f"{KEY_PREFIX}{key_id}_{secret}", hash_secret(secret)


def split_token(token: str) -> tuple[str, str] | None:
    """``(key_id, secret)`` of a well-formed token, else None."""
    if not token.startswith(KEY_PREFIX):
        return None
    key_id, sep, secret = token[len(KEY_PREFIX):].partition("_")
    if not sep or len(key_id) != 12 or not secret or len(token) > 200:
        return None
    return key_id, secret


def verify(stored_hash: str, secret: str) -> bool:
    """Constant-time comparison of a presented secret with the stored hash."""
    return hmac.compare_digest(stored_hash.encode(), hash_secret(secret).encode())
