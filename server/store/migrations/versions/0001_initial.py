"""Initial schema: measurements (append-only chain), images, config versions, tokens.

Revision ID: 0001
Revises:
Create Date: 2026-11-21
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

from server.store.models import UTCDateTime

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def _id() -> sa.Column:
    return sa.Column("id", sa.BigInteger().with_variant(sa.Integer, "sqlite"), primary_key=True)


def upgrade() -> None:
    op.create_table(
        "measurements",
        _id(),
        sa.Column("station", sa.String(64), nullable=False),
        sa.Column("seq", sa.BigInteger, nullable=False),
        sa.Column("stored_at", UTCDateTime(), nullable=False),
        sa.Column("triggered_at", UTCDateTime(), nullable=False),
        sa.Column("trigger_id", sa.BigInteger, nullable=False),
        sa.Column("part_id", sa.String(64), nullable=True),
        sa.Column("recipe", sa.String(64), nullable=False),
        sa.Column("recipe_version", sa.Integer, nullable=False),
        sa.Column("result", sa.String(3), nullable=False),
        sa.Column("reason_code", sa.Integer, nullable=False),
        sa.Column("reason", sa.String(64), nullable=False),
        sa.Column("body", sa.Text, nullable=False),
        sa.Column("prev_hash", sa.String(64), nullable=False),
        sa.Column("hash", sa.String(64), nullable=False, unique=True),
        sa.UniqueConstraint("station", "seq", name="uq_measurements_station_seq"),
    )
    op.create_index("ix_measurements_station_time", "measurements", ["station", "triggered_at"])
    op.create_index("ix_measurements_station_part", "measurements", ["station", "part_id"])
    op.create_table(
        "images",
        _id(),
        sa.Column(
            "measurement_id",
            sa.BigInteger().with_variant(sa.Integer, "sqlite"),
            sa.ForeignKey("measurements.id"),
            nullable=False,
        ),
        sa.Column("view", sa.Integer, nullable=False),
        sa.Column("camera_id", sa.String(64), nullable=False),
        sa.Column("path", sa.String(400), nullable=False, unique=True),
        sa.Column("bytes", sa.BigInteger, nullable=False),
        sa.Column("ok", sa.Boolean, nullable=False),
        sa.Column("created_at", UTCDateTime(), nullable=False),
        sa.Column("evicted_at", UTCDateTime(), nullable=True),
    )
    op.create_index("ix_images_measurement_id", "images", ["measurement_id"])
    op.create_index("ix_images_evict", "images", ["evicted_at", "ok", "id"])
    op.create_table(
        "config_versions",
        _id(),
        sa.Column("station", sa.String(64), nullable=False),
        sa.Column("kind", sa.String(16), nullable=False),
        sa.Column("name", sa.String(64), nullable=False),
        sa.Column("version", sa.Integer, nullable=False),
        sa.Column("content", sa.Text, nullable=False),
        sa.Column("sha256", sa.String(64), nullable=False),
        sa.Column("created_at", UTCDateTime(), nullable=False),
        sa.Column("created_by", sa.String(64), nullable=False),
        sa.Column("comment", sa.String(400), nullable=False),
        sa.UniqueConstraint("station", "kind", "name", "version", name="uq_config_versions"),
    )
    op.create_table(
        "active_versions",
        sa.Column("station", sa.String(64), primary_key=True),
        sa.Column("kind", sa.String(16), primary_key=True),
        sa.Column("name", sa.String(64), primary_key=True),
        sa.Column(
            "version_id",
            sa.BigInteger().with_variant(sa.Integer, "sqlite"),
            sa.ForeignKey("config_versions.id"),
            nullable=False,
        ),
        sa.Column("activated_at", UTCDateTime(), nullable=False),
        sa.Column("activated_by", sa.String(64), nullable=False),
    )
    op.create_table(
        "tokens",
        _id(),
        sa.Column("name", sa.String(64), nullable=False, unique=True),
        sa.Column("role", sa.String(16), nullable=False),
        sa.Column("token_sha256", sa.String(64), nullable=False, unique=True),
        sa.Column("created_at", UTCDateTime(), nullable=False),
        sa.Column("revoked_at", UTCDateTime(), nullable=True),
    )
    _append_only("measurements")


def _append_only(table: str) -> None:
    """Refuse UPDATE and DELETE in the database itself, so no code path can rewrite the trail."""
    if op.get_bind().dialect.name == "sqlite":
        for action in ("UPDATE", "DELETE"):
            op.execute(
                f"CREATE TRIGGER {table}_no_{action.lower()} BEFORE {action} ON {table} "
                f"BEGIN SELECT RAISE(ABORT, '{table} is append-only'); END"
            )
    else:
        op.execute(
            "CREATE FUNCTION mvpose_append_only() RETURNS trigger LANGUAGE plpgsql AS $$ "
            "BEGIN RAISE EXCEPTION '% is append-only', TG_TABLE_NAME; END $$"
        )
        op.execute(
            f"CREATE TRIGGER {table}_append_only BEFORE UPDATE OR DELETE ON {table} "
            "FOR EACH ROW EXECUTE FUNCTION mvpose_append_only()"
        )


def downgrade() -> None:
    if op.get_bind().dialect.name == "sqlite":
        op.execute("DROP TRIGGER IF EXISTS measurements_no_update")
        op.execute("DROP TRIGGER IF EXISTS measurements_no_delete")
    else:
        op.execute("DROP TRIGGER IF EXISTS measurements_append_only ON measurements")
        op.execute("DROP FUNCTION IF EXISTS mvpose_append_only()")
    for table in ("tokens", "active_versions", "config_versions", "images", "measurements"):
        op.drop_table(table)
