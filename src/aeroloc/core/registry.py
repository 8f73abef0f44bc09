"""Model registries: ``retrieval`` (global descriptors) and ``local`` (keypoints, descriptors, matchers)."""

import importlib

from aeroloc.core.errors import AerolocError


def lazy_class(table: dict[str, str], package: str, kind: str, name: str):
    """The class a registry ``table`` names as ``"module:Class"`` under ``package``, imported on first use so
    listing a registry does not import every architecture; unknown or missing names are clear errors."""
    if name not in table:
        raise AerolocError(f"unknown {kind} '{name}'; choose one of: {', '.join(sorted(table))}")
    module, cls = table[name].split(":")
    try:
        mod = importlib.import_module(f"{package}.{module}")
    except ModuleNotFoundError as exc:
        if exc.name == f"{package}.{module}":
            raise AerolocError(
                f"{kind} '{name}' is not available in this build (module {package}.{module} is missing)"
            ) from None
        raise
    return getattr(mod, cls)
