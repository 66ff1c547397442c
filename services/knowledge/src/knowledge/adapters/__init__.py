"""One store per backend: memory, sqlite, redis, memcached (see :mod:`knowledge.ports`)."""

__all__: list[str] = []
