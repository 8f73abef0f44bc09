"""Retrieval stage: global descriptor of each query -> Faiss search -> top-N tile ids with scores."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from aeroloc.database import Database
from aeroloc.extract import describe_image
from aeroloc.index import search


@dataclass
class Retrieval:
    tile_ids: list[str]
    scores: list[float]
    times_ms: dict = field(default_factory=dict)  # descriptor, search


class Retriever:
    """Holds a database's method, descriptors and index; ``__call__(image)`` retrieves top-N tiles."""

    def __init__(self, db: Database, method: str | None = None, device="cpu"):
        self.db = db
        self.model, self.store, self.index, self.entry = db.load_method(method, device)
        self.method = method or db.meta.get("default_method")
        self.device = device

    def __call__(self, image: np.ndarray, top_n: int) -> Retrieval:
        desc, t_desc = describe_image(self.model, image, self.device)
        t0 = time.perf_counter()
        scores, ids = search(self.index, desc, top_n)
        t_search = (time.perf_counter() - t0) * 1000
        tiles = self.db.tiles
        return Retrieval([tiles[i].id for i in ids[0] if i >= 0], [float(s) for s in scores[0][ids[0] >= 0]],
                         {"descriptor": t_desc, "search": t_search})
