"""Fixtures shared by the server tests: the throwaway PostgreSQL cluster (see postgres.py)."""

from postgres import postgres_cluster  # noqa: F401  (registers the session fixture)
