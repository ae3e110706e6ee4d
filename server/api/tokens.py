"""Token endpoints (engineer only): create (the secret is shown once), list, revoke."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path
from pydantic import BaseModel, Field

from server.api.deps import EngineerUser, StoreDep
from server.api.openapi import problem_responses
from server.auth import Role, create_token
from server.store.tokens import TokenInfo

router = APIRouter(prefix="/tokens", tags=["tokens"])


class TokenRequest(BaseModel):
    name: str = Field(pattern=r"^[A-Za-z0-9_.\-]+$", min_length=1, max_length=64)
    role: Role


class NewToken(BaseModel):
    info: TokenInfo
    token: str = Field(description="the secret; shown only in this response")


@router.post("", response_model=NewToken, status_code=201, responses=problem_responses(409))
def create(request: TokenRequest, _: EngineerUser, store: StoreDep) -> NewToken:
    """Create a token with a role; store the returned secret, it cannot be shown again.
    A revoked token's name may be used again; a live one's is a 409."""
    secret, info = create_token(store.tokens, request.name, request.role)
    return NewToken(info=info, token=secret)


@router.get("", response_model=list[TokenInfo])
def list_tokens(_: EngineerUser, store: StoreDep) -> list[TokenInfo]:
    """Every token (names and roles, never secrets)."""
    return store.tokens.list()


@router.delete("/{name}", response_model=TokenInfo, responses=problem_responses(409))
def revoke(
    name: Annotated[str, Path(max_length=64)], _: EngineerUser, store: StoreDep
) -> TokenInfo:
    """Revoke a token; requests with it fail from now on. The last live engineer token cannot
    be revoked (409): nobody could manage tokens any more."""
    return store.tokens.revoke(name)
