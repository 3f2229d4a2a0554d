"""Alembic migrations of the cranetwin schema, applied programmatically by ``Store.open``."""
