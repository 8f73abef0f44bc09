"""EigenPlaces (Berton et al., ICCV 2023): the CosPlace network (CNN -> L2 -> GeM -> FC -> L2) trained to be
robust to viewpoint changes.

The authors' ``GeoLocalizationNet_`` (gmberton/EigenPlaces, eigenplaces_model/eigenplaces_network.py) has the
same modules and key names as CosPlace's (``backbone.<i>``, ``aggregation.1.p``, ``aggregation.3.weight``);
only the released (backbone, dim) pairs and the URL differ:
``https://github.com/gmberton/EigenPlaces/releases/download/v1.0/{backbone}_{dim}_eigenplaces.pth``.
"""

from __future__ import annotations

from aeroloc.retrieval.models.cosplace import CosPlace


class EigenPlaces(CosPlace):
    """EigenPlaces trained on SF-XL. conf: backbone (VGG16, ResNet18/50/101), dim (see AVAILABLE), resize
    (square side; training used 512 x 512 images)."""

    default_conf = {"backbone": "ResNet50", "dim": 2048, "resize": 512}
    # authors' hubconf.py AVAILABLE_TRAINED_MODELS
    AVAILABLE = {
        "VGG16": [512],
        "ResNet18": [256, 512],
        "ResNet50": [128, 256, 512, 1024, 2048],
        "ResNet101": [128, 256, 512, 1024, 2048],
    }
    URL = "https://github.com/gmberton/EigenPlaces/releases/download/v1.0/{backbone}_{dim}_eigenplaces.pth"
    NAME = "EigenPlaces"
