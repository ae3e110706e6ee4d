"""The server's endpoint and its security: its name, application URI and address, the security
policies the station file lists (Basic256Sha256 Sign / SignAndEncrypt; None only when listed),
the identity tokens (user name, anonymous when allowed), which client certificates it accepts
(:mod:`.certificates`), and channels of an unlisted security kept to discovery
(:mod:`.access`). The roles' ruleset (:class:`~.access.Roles`) guards every session's requests.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from asyncua import Server, ua

from .access import Roles, keep_unlisted_to_discovery
from .certificates import validate_clients
from .settings import OpcUaLinkConfig

POLICIES = {
    "Basic256Sha256_Sign": ua.SecurityPolicyType.Basic256Sha256_Sign,
    "Basic256Sha256_SignAndEncrypt": ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt,
    "None": ua.SecurityPolicyType.NoSecurity,
}


async def set_up(server: Server, cfg: OpcUaLinkConfig, roles: Roles, pki: Path | None,
                 error: Callable[[str], None]) -> None:
    """Set up an initialised ``server``'s endpoint and security before it starts: ``pki`` is
    the folder of the server's certificate and key (:func:`.certificates.make_certificate`;
    None when no secure policy is listed), ``error`` hears why a client's certificate was
    refused."""
    server.set_server_name("mvpose station")
    await server.set_application_uri(cfg.application_uri)
    server.set_endpoint(f"opc.tcp://{cfg.host}:{cfg.port}/mvpose")
    server.set_security_policy([POLICIES[p] for p in cfg.security],
                               permission_ruleset=roles)
    tokens: list[type] = [ua.UserNameIdentityToken]
    if cfg.allow_anonymous:
        tokens.append(ua.AnonymousIdentityToken)
    server.set_identity_tokens(tokens)
    if pki is not None:
        await validate_clients(server, pki, cfg.trust_all_client_certificates, error)
    keep_unlisted_to_discovery(server, [POLICIES[p] for p in cfg.security],
                               list(POLICIES.values()))
