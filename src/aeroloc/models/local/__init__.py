"""Registry of local features and matchers (re-rankers), selected by name (``--rerank NAME``).

Filled by :mod:`aeroloc.models.local.registry`; see ``base.py`` for the contracts.
"""

from aeroloc.models.local.registry import (  # noqa: F401
    DEFAULT_RERANKER,
    EXTRACTORS,
    MATCHERS,
    RERANKERS,
    build_extractor,
    build_matcher,
    build_reranker,
    reranker_conf,
)
