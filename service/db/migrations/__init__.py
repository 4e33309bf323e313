"""Alembic migrations of the scene store (service/db/rows.py); run by :mod:`service.db.migrate`."""
