"""List the retrieval methods and re-rankers, and whether their weights are available on this machine."""

from __future__ import annotations


def add_arguments(p):
    p.add_argument("--check", action="store_true", help="look for each method's weights (no download)")


def run(args) -> int:
    from aeroloc.core.errors import AerolocError
    from aeroloc.core.weights import resolve_weights
    from aeroloc.matching.registry import DEFAULT_RERANKER, RERANKERS
    from aeroloc.retrieval.models import DEFAULT_METHOD, METHODS, method_class

    print("retrieval methods (--method):")
    for name in METHODS:
        line = f"  {name}{' (default)' if name == DEFAULT_METHOD else ''}"
        if args.check:
            try:
                import torch

                with torch.device("meta"):  # the default variant's weight source, without allocating weights
                    src = getattr(method_class(name)(), "weight_source", None)
                line += ": " + ("ready" if src is None else f"weights at {resolve_weights(src, download=False)}")
            except AerolocError as exc:
                line += f": {exc}"
        print(line)
    print("re-rankers (--rerank):")
    for name, conf in RERANKERS.items():
        print(
            f"  {name}{' (default)' if name == DEFAULT_RERANKER else ''}: "
            f"{conf['extractor']['name']} + {conf['matcher']['name']}"
        )
    return 0
