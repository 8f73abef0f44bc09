"""Registry of local features and matchers (re-rankers), selected by name (``--rerank NAME``).

Filled by :mod:`aeroloc.models.local.registry`; see ``base.py`` for the contracts.
"""
