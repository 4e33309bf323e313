"""Alembic migrations of the scene store (service/store.py); run by :mod:`service.migrate`."""
