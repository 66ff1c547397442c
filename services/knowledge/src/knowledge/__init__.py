"""The knowledge service: versioned, causal, historical knowledge and a model store.

    async with open_service(KnowledgeConfig(system="demo"), fabric=fabric) as service:
        ...

or as a process: ``python -m knowledge --system demo``. Errors: :mod:`knowledge.errors`.
"""

from .app import open_service, open_store
from .config import HistoryRule, KnowledgeConfig
from .service import KnowledgeService, ServiceStats

__all__ = [
    "HistoryRule",
    "KnowledgeConfig",
    "KnowledgeService",
    "ServiceStats",
    "open_service",
    "open_store",
]
