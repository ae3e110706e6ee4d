"""Who may do what on the OPC UA link: users from the station file, roles per service and method,
and channels of a security the station file does not list (None among them) kept to discovery."""

from __future__ import annotations

import hashlib
import logging
import os
from pathlib import Path
from typing import Any

from asyncua import Server, ua
from asyncua.common.utils import Buffer, ServiceError
from asyncua.crypto.permission_rules import USER_TYPES, SimpleRoleRuleset, User, UserRole
from asyncua.crypto.security_policies import (
    SECURITY_POLICY_TYPE_MAP,
    CryptographyNone,
    SecurityPolicy,
    SecurityPolicyFactory,
    SecurityPolicyNone,
)
from asyncua.server.user_managers import UserManager
from asyncua.ua.ua_binary import struct_from_binary

from .settings import OpcUaLinkConfig, check_password

log = logging.getLogger(__name__)
_UA: Any = ua


def default_pki_dir() -> Path:
    """``<data_dir>/opcua`` when the station file names no pki_dir (MVPOSE_DATA_DIR, else var)."""
    return Path(os.environ.get("MVPOSE_DATA_DIR", "var")) / "opcua"


# ---------------------------------------------------------------------------- users and roles
class Users(UserManager):
    """asyncua's user manager: user name + password against the station file's hashes."""

    def __init__(self, config: OpcUaLinkConfig) -> None:
        self.config = config
        self._good: set[tuple[str, str]] = set()  # (name, sha256 of a checked password)

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> User | None:
        if username is None:
            return User(role=UserRole.Anonymous) if self.config.allow_anonymous else None
        user = self.config.users.get(username)
        if user is None or password is None:
            log.warning("OPC UA: login refused for unknown user %r", username)
            return None
        key = (username, hashlib.sha256(password.encode()).hexdigest())
        if key not in self._good:
            if not check_password(password, user.password_hash):
                log.warning("OPC UA: wrong password for user %r", username)
                return None
            self._good.add(key)  # pbkdf2 runs on the station loop: once per user and password
        return User(role=UserRole.User, name=username)


class Roles(SimpleRoleRuleset):
    """read: browse, read, subscribe; operator: + call methods; engineer: + write, and the
    methods in ``engineer_methods`` (ActivateConfiguration), which an operator's call is
    refused (BadUserAccessDenied, the whole call) like a reader's."""

    CALL = _UA.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)
    WRITE = _UA.NodeId(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary)

    def __init__(self, config: OpcUaLinkConfig) -> None:
        super().__init__()
        self.config = config
        every = {_UA.NodeId(t) for t in USER_TYPES}
        read = every - {self.CALL, self.WRITE}
        self.allowed = {"read": read, "operator": read | {self.CALL}, "engineer": every}
        self.engineer_methods: set[ua.NodeId] = set()  # filled once the model is built

    def role(self, user: User | None) -> str | None:
        if user is None:
            return None
        if user.name is not None and user.name in self.config.users:
            return self.config.users[user.name].role
        if user.role == UserRole.Anonymous and self.config.allow_anonymous:
            return "read"
        return None

    def check_validity(self, user: Any, action_type_id: Any, body: Any) -> bool:
        role = self.role(user)
        if role is None or action_type_id not in self.allowed[role]:
            return False
        if action_type_id == self.CALL and role != "engineer" and self.engineer_methods:
            return not self._calls_engineer_method(body)
        return True

    def _calls_engineer_method(self, body: Any) -> bool:
        """Whether a CallRequest's body (its parameters, not read yet) calls one of the
        engineer's methods; read from a copy, the server decodes the body itself after us."""
        if not isinstance(body, Buffer):
            return True  # not what asyncua hands us: refuse rather than guess
        params = struct_from_binary(ua.CallParameters, body.copy())
        return any(m.MethodId in self.engineer_methods for m in params.MethodsToCall or [])



# ---------------------------------------------------------------------------- unlisted security
class _NoSessions(CryptographyNone):
    """The None channel's asymmetric part: as None, but no client signature is ever valid.
    asyncua checks the client's signature (verify) only in ActivateSession on a None channel
    (its chunks carry no signature), so ActivateSession is refused there before the user's
    token is read."""

    def verify(self, data: bytes, signature: bytes) -> None:
        raise ServiceError(ua.StatusCodes.BadSecurityPolicyRejected)


class _OnlyDiscovery(SimpleRoleRuleset):
    """No service of a session on a discovery-only channel (discovery needs none)."""

    def check_validity(self, user: Any, action_type_id: Any, body: Any) -> bool:
        raise ServiceError(ua.StatusCodes.BadSecurityPolicyRejected)


def _refuse_sessions(policy: SecurityPolicy) -> str:
    """asyncua's server reads ``AsymmetricSignatureURI`` only to sign its CreateSession answer
    (a channel's own messages use the policy's crypto objects): so CreateSession is refused,
    before a client sends a user token. A later asyncua that read it elsewhere would break
    discovery on such a channel, which the tests do."""
    raise ServiceError(ua.StatusCodes.BadSecurityPolicyRejected)


def discovery_only(cls: type[SecurityPolicy]) -> type[SecurityPolicy]:
    """``cls`` for a secure channel of a policy and mode the station file does not list.

    OPC UA keeps the None channel open for discovery (GetEndpoints, FindServers: OPC 10000-4
    §5.4), and asyncua let a client that asked for it anyway open a session there, send its
    password in clear and call methods unchecked by the roles (a None channel has no roles).
    On such a channel CreateSession is refused, and behind it ActivateSession and every service
    of a session: BadSecurityPolicyRejected. A Basic256Sha256 channel of a mode that is not
    listed is opened the same way, discovery only, so such a client learns at once why (asyncua
    would not answer its OpenSecureChannel at all)."""

    def init(self: SecurityPolicy, *args: Any, **kwargs: Any) -> None:
        cls.__init__(self, *args, **kwargs)
        self.permissions = _OnlyDiscovery()
        if cls is SecurityPolicyNone:
            self.asymmetric_cryptography = _NoSessions()

    return type(f"DiscoveryOnly{cls.__name__}", (cls,),
                {"__init__": init, "AsymmetricSignatureURI": property(_refuse_sessions),
                 "__doc__": discovery_only.__doc__})


def keep_unlisted_to_discovery(server: Server, listed: list[ua.SecurityPolicyType],
                               known: list[ua.SecurityPolicyType]) -> list[str]:
    """Channels of the ``known`` policies (the station file's choices) that are not ``listed``
    become :func:`discovery_only`; the secure ones only once the server has its certificate.
    Before ``server.start()``: asyncua hands its list of policies to every connection. Returns
    what was added, as "<policy>#<mode>"."""
    added = []
    for kind in known:
        if kind in listed:
            continue
        cls: type[SecurityPolicy]
        mode: ua.MessageSecurityMode
        cls, mode, _ = SECURITY_POLICY_TYPE_MAP[kind]  # type: ignore[assignment]
        cert, key = server.iserver.certificate, server.iserver.private_key
        if cls is not SecurityPolicyNone and (cert is None or key is None):
            continue  # no secure channel at all without a certificate
        factory = SecurityPolicyFactory(discovery_only(cls), mode, cert, key)
        server._policies.insert(0, factory)  # noqa: SLF001 - asyncua has no public hook for it
        added.append(f"{cls.URI.rsplit('#', 1)[-1]}#{mode.name}")
    return added
