"""One store per backend: memory, sqlite, redis (see :mod:`knowledge.ports`)."""

__all__: list[str] = []
