"""Alembic environment: migrations run on the connection the store hands over (never a URL here)."""

from __future__ import annotations

from alembic import context

from server.store.models import Base

connection = context.config.attributes.get("connection")
if connection is None:
    raise RuntimeError(
        "server.store migrations run through server.store.db.migrate(engine), "
        "which passes the connection; there is no alembic.ini URL"
    )
context.configure(
    connection=connection,
    target_metadata=Base.metadata,
    render_as_batch=connection.dialect.name == "sqlite",
)
with context.begin_transaction():
    context.run_migrations()
