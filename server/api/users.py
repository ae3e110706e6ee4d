"""User endpoints (engineer only): the operator page's people, their PIN or password, role,
disabling, and their audit trail (server/users.py holds the policy)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Path, Query
from pydantic import BaseModel, ConfigDict, Field, field_validator

from server.api.deps import EngineerUser, StoreDep
from server.api.openapi import problem_responses
from server.auth import Role
from server.errors import InvalidInputError
from server.store.schemas import MAX_ID
from server.store.users import UserEvent, UserInfo
from server.users import (
    NAME_PATTERN,
    PASSWORD_MAX,
    PASSWORD_MIN,
    PIN_PATTERN,
    SecretKind,
    add_user,
    check_secret,
    reset_user,
)

router = APIRouter(tags=["users"])
Name = Annotated[str, Path(max_length=64)]


def _checked(kind: SecretKind, secret: str) -> str:
    # The schema states the same rules (pattern, lengths); these are the words for them.
    try:
        check_secret(kind, secret)
    except InvalidInputError as err:
        raise ValueError(err.detail) from None
    return secret


class PinSecret(BaseModel):
    model_config = ConfigDict(extra="forbid")

    kind: Literal["pin"]
    secret: str = Field(description="4 to 8 digits", json_schema_extra={
        "pattern": PIN_PATTERN.pattern, "minLength": 4, "maxLength": 8})

    @field_validator("secret")
    @classmethod
    def _rules(cls, secret: str) -> str:
        return _checked(SecretKind.PIN, secret)


class PasswordSecret(BaseModel):
    model_config = ConfigDict(extra="forbid")

    kind: Literal["password"]
    secret: str = Field(description="10 to 200 characters", json_schema_extra={
        "minLength": PASSWORD_MIN, "maxLength": PASSWORD_MAX})

    @field_validator("secret")
    @classmethod
    def _rules(cls, secret: str) -> str:
        return _checked(SecretKind.PASSWORD, secret)


NewSecret = Annotated[PinSecret | PasswordSecret, Field(discriminator="kind")]


class _NewUser(BaseModel):
    name: str = Field(pattern=NAME_PATTERN, min_length=1, max_length=64)
    role: Role


class PinUser(_NewUser, PinSecret):
    """A user who logs in with a PIN."""


class PasswordUser(_NewUser, PasswordSecret):
    """A user who logs in with a password."""


UserRequest = Annotated[PinUser | PasswordUser, Field(discriminator="kind")]


class UserChange(BaseModel):
    model_config = ConfigDict(extra="forbid")

    role: Role | None = Field(None, description="applies to the user's open pages at once")
    disabled: bool | None = Field(None, strict=True,
                                  description="true ends the user's open pages at once")


@router.post("/users", response_model=UserInfo, status_code=201,
             responses=problem_responses(409))
def create(request: UserRequest, who: EngineerUser, store: StoreDep) -> UserInfo:
    """Add a user who logs in on the operator page with a PIN or a password (409: name taken)."""
    return add_user(store.users, request.name, request.role, SecretKind(request.kind),
                    request.secret, who.name)


@router.get("/users", response_model=list[UserInfo])
def list_users(_: EngineerUser, store: StoreDep) -> list[UserInfo]:
    """Every user: role, PIN or password, disabled, locked, wrong secrets in a row."""
    return store.users.list()


@router.get("/user-events", response_model=list[UserEvent])
def events(
    _: EngineerUser, store: StoreDep,
    user: Annotated[str | None, Query(max_length=64)] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    before_id: Annotated[int | None, Query(ge=1, le=MAX_ID)] = None,
) -> list[UserEvent]:
    """The users' audit trail, newest first: logins, wrong secrets, refusals, locks, changes."""
    return store.users.events(user, limit, before_id)


@router.get("/users/{name}", response_model=UserInfo)
def get_user(name: Name, _: EngineerUser, store: StoreDep) -> UserInfo:
    """One user."""
    return store.users.info(name)


@router.patch("/users/{name}", response_model=UserInfo)
def change(name: Name, body: UserChange, who: EngineerUser, store: StoreDep) -> UserInfo:
    """Change a user's role, or disable or enable it; open pages follow at once."""
    info = store.users.info(name)
    if body.role is not None and body.role.value != info.role:
        info = store.users.set_role(name, body.role.value, who.name)
    if body.disabled is True and info.disabled_at is None:
        info = store.users.disable(name, who.name)
    elif body.disabled is False and info.disabled_at is not None:
        info = store.users.enable(name, who.name)
    return info


@router.post("/users/{name}/reset", response_model=UserInfo)
def reset(name: Name, body: NewSecret, who: EngineerUser, store: StoreDep) -> UserInfo:
    """A new PIN or password: unlocks the user and ends its open pages."""
    return reset_user(store.users, name, SecretKind(body.kind), body.secret, who.name)
