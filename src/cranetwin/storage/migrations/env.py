"""Alembic environment: runs on the connection :func:`cranetwin.storage.engine.migrate` passes."""

from __future__ import annotations

from alembic import context

from cranetwin.storage import (  # noqa: F401  (register tables)
    blocks,
    events,
    machines,
    payloads,
    summaries,
)
from cranetwin.storage.base import Base

connection = context.config.attributes["connection"]
context.configure(connection=connection, target_metadata=Base.metadata,
                  render_as_batch=connection.dialect.name == "sqlite")
with context.begin_transaction():
    context.run_migrations()
