"""Users of the operator page (PIN or password) and their append-only audit trail
(docs/operator-page.md, "Users").

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-27
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

from server.store.models import UTCDateTime

revision = "0006"
down_revision = "0005"
branch_labels = None
depends_on = None

_ID = sa.BigInteger().with_variant(sa.Integer, "sqlite")


def upgrade() -> None:
    op.create_table(
        "users",
        sa.Column("id", _ID, primary_key=True),
        sa.Column("name", sa.String(64), nullable=False, unique=True),
        sa.Column("role", sa.String(16), nullable=False),
        sa.Column("secret_kind", sa.String(8), nullable=False),
        sa.Column("secret_hash", sa.String(200), nullable=False),
        sa.Column("created_at", UTCDateTime(), nullable=False),
        sa.Column("disabled_at", UTCDateTime(), nullable=True),
        sa.Column("failed_count", sa.Integer, nullable=False),
        sa.Column("last_failed_at", UTCDateTime(), nullable=True),
        sa.Column("locked_at", UTCDateTime(), nullable=True),
        sa.Column("epoch", sa.Integer, nullable=False),
    )
    op.create_table(
        "user_events",
        sa.Column("id", _ID, primary_key=True),
        sa.Column("at", UTCDateTime(), nullable=False),
        sa.Column("station", sa.String(64), nullable=False),
        sa.Column("user_name", sa.String(64), nullable=False),
        sa.Column("event", sa.String(16), nullable=False),
        sa.Column("actor", sa.String(64), nullable=False),
        sa.Column("detail", sa.Text, nullable=False),
    )
    op.create_index("ix_user_events_user", "user_events", ["user_name", "id"])
    # An audit trail: no UPDATE, DELETE or TRUNCATE, as for measurements (0001, 0003).
    if op.get_bind().dialect.name == "sqlite":
        for action in ("UPDATE", "DELETE"):
            op.execute(
                f"CREATE TRIGGER user_events_no_{action.lower()} BEFORE {action} ON "
                "user_events BEGIN SELECT RAISE(ABORT, 'user_events is append-only'); END"
            )
    else:
        op.execute(
            "CREATE TRIGGER user_events_append_only BEFORE UPDATE OR DELETE ON user_events "
            "FOR EACH ROW EXECUTE FUNCTION mvpose_append_only()"
        )
        op.execute(
            "CREATE TRIGGER user_events_no_truncate BEFORE TRUNCATE ON user_events "
            "FOR EACH STATEMENT EXECUTE FUNCTION mvpose_append_only()"
        )


def downgrade() -> None:
    if op.get_bind().dialect.name == "sqlite":
        op.execute("DROP TRIGGER IF EXISTS user_events_no_update")
        op.execute("DROP TRIGGER IF EXISTS user_events_no_delete")
    else:
        op.execute("DROP TRIGGER IF EXISTS user_events_append_only ON user_events")
        op.execute("DROP TRIGGER IF EXISTS user_events_no_truncate ON user_events")
    op.drop_index("ix_user_events_user", table_name="user_events")
    op.drop_table("user_events")
    op.drop_table("users")
