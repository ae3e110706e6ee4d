"""The OPC UA backend's settings: the station file's ``links.opcua`` block (docs/opcua.md),
and the hashed form its users' passwords are kept in."""

from __future__ import annotations

import base64
import hashlib
import hmac
import os
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


PBKDF2 = "pbkdf2_sha256"


def hash_password(password: str, iterations: int = 100_000, salt: bytes | None = None) -> str:
    """The form a station file keeps a link user's password in (never the password itself):
    ``pbkdf2_sha256$<iterations>$<salt, base64>$<key, base64>``."""
    salt = salt if salt is not None else os.urandom(16)
    key = hashlib.pbkdf2_hmac("sha256", password.encode(), salt, iterations)
    return "$".join((PBKDF2, str(iterations), base64.b64encode(salt).decode(),
                     base64.b64encode(key).decode()))


def check_password(password: str, stored: str) -> bool:
    """``password`` matches ``stored`` (a :func:`hash_password` string)."""
    algo, iterations, salt, key = stored.split("$")
    if algo != PBKDF2:
        return False
    got = hashlib.pbkdf2_hmac("sha256", password.encode(), base64.b64decode(salt),
                              int(iterations))
    return hmac.compare_digest(got, base64.b64decode(key))


class OpcUaUser(_Model):
    """One OPC UA user: its role and its password's hash (:func:`hash_password`)."""

    role: Literal["read", "operator", "engineer"]
    password_hash: str = Field(description="pbkdf2_sha256$<iterations>$<salt>$<key> "
                                           "(drivers.links.opcua.settings.hash_password)")

    @field_validator("password_hash")
    @classmethod
    def _hashed(cls, value: str) -> str:
        parts = value.split("$")
        ok = len(parts) == 4 and parts[0] == PBKDF2 and parts[1].isdigit()
        if ok:
            try:
                base64.b64decode(parts[2], validate=True)
                base64.b64decode(parts[3], validate=True)
            except ValueError:
                ok = False
        if not ok or int(parts[1]) < 10_000:
            raise ValueError(
                "password_hash must be pbkdf2_sha256$<iterations >= 10000>$<salt>$<key> as "
                "drivers.links.opcua.settings.hash_password writes it, never a plain password")
        return value


OpcUaSecurity = Literal["Basic256Sha256_Sign", "Basic256Sha256_SignAndEncrypt", "None"]


class OpcUaLinkConfig(_Model):
    """OPC UA server with the Machine Vision model, OPC 40100-1 (docs/opcua.md)."""

    enabled: bool = True
    host: str = Field("127.0.0.1", description="address to listen on (0.0.0.0: every interface)")
    port: int = Field(4840, ge=0, le=65535, description="TCP port (0: any free port, tests)")
    security: tuple[OpcUaSecurity, ...] = Field(
        ("Basic256Sha256_SignAndEncrypt", "Basic256Sha256_Sign"), min_length=1,
        description="endpoints offered; \"None\" (no signing, no encryption) only when listed")
    users: dict[str, OpcUaUser] = Field(
        default_factory=dict, description="user name -> role and password hash")
    allow_anonymous: bool = Field(
        False, description="a client without a user name may connect, with the read role")
    trust_all_client_certificates: bool = Field(
        False, description="accept any client certificate (default: only those in "
                           "<pki_dir>/trusted; refused ones are kept in <pki_dir>/rejected)")
    pki_dir: str | None = Field(
        None, description="the server's certificate and key (made at first start) and the "
                          "trusted client certificates; default <data_dir>/opcua")
    application_uri: str = Field("urn:mvpose:station", min_length=1,
                                 description="the server's ApplicationUri (in its certificate)")
    measure_timeout_s: float | None = Field(
        None, gt=0, le=600,
        description="the link's own backstop; default: the station deadline + 2 s, a second "
                    "behind the station's own watchdog")
    query_spacing_s: float = Field(
        0.25, ge=0, le=60,
        description="result, recipe and configuration management calls start at most this "
                    "often, whichever client calls (each keeps the station process busy for "
                    "tens of milliseconds beside the trigger thread)")

    @field_validator("security")
    @classmethod
    def _distinct(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        if len(set(value)) != len(value):
            raise ValueError(f"security lists a policy twice: {list(value)}")
        return value
