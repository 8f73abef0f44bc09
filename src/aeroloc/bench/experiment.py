"""Experiment files: one YAML names the maps, query sets, methods and the sweep (zooms, overlaps, N, K …).

Example (all keys; only ``name``, ``maps``, ``queries`` and ``methods`` are required)::

    name: paper-zoom
    maps:
      - {name: naip-nd, path: ../shared/data/naip-nd/map_20200831.tif, tile_m: null}
    queries:
      - {name: naip-nd/dev, path: ../shared/data/naip-nd/dev/queries.csv, map: naip-nd, limit: 40, north_up: true}
    methods: [xfeat-vlad]            # aeroloc.retrieval.models.METHODS
    rerankers: [none]                # none = retrieval only; else aeroloc.matching.registry.RERANKERS
    zooms: [0.5, 1, 1.5, 2]          # > 0
    overlaps: [0]                    # in [0, 1)
    top_n: [20]                      # retrieved candidates (re-ranked when a re-ranker is set)
    top_k: 1                         # re-ranked candidates kept for alignment
    thresholds_m: [10, 25, 50, 100]  # Georeference Recall distances
    device: auto
    output: runs/paper-zoom          # results.sqlite, tables, plots, report-<run>.html
    cache: runs/cache                # tile sets, descriptors, features, indexes (default <output>/cache)

Relative paths (map/queries paths, ``output``, ``cache``) are resolved against the *project root of the YAML
file*: the nearest folder, starting at the YAML's own folder and going up, that holds ``pyproject.toml`` or
``.git``; when there is none, against the YAML's folder. So ``experiments/x.yaml`` in the repo writes
``../shared/data`` for the shared data beside the repo. ``~`` and ``$VARS`` are expanded first.

``limit: n`` on a query set keeps an evenly spaced subset of n queries (:func:`sample_queries`, applied by the
pipeline), so slow re-rankers fit a time budget while every part of the set (dates, cameras) stays represented.
``local_turns: true`` on a map builds its tiles' local features at eight turns too (``aeroloc build
--local-turns``): photos of unknown heading are then extracted once for their screens. ``global_turns: true``
builds its tiles' global descriptors at eight turns too (``aeroloc build --global-turns``): a photo of unknown
heading retrieves its place with one descriptor.
``north_up: true`` says the set's images are north-up (``aeroloc localize --north-up``): no rotation search.
``query_gsd: 5`` gives the images' ground resolution in metres per pixel (``aeroloc localize --query-gsd 5``): the
dense structural stage is tried before the re-ranker. Both apply to configurations with a re-ranker only.
``priors: none | rough | exact`` (default ``auto``: what the file says, see aeroloc.core.priors) sets what the
queries' per-query priors are; ``rough`` adds sensor-like noise with ``seed`` (default 0).

Retrieval-only configurations (re-ranker ``none``) do not depend on N beyond the longest list (Recall@N is
computed for every N up to it), so they are swept once with the largest ``top_n``.
"""

from __future__ import annotations

import hashlib
import itertools
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

from aeroloc.core.errors import AerolocError

KEYS = {
    "name",
    "description",
    "maps",
    "queries",
    "methods",
    "rerankers",
    "zooms",
    "overlaps",
    "top_n",
    "top_k",
    "thresholds_m",
    "device",
    "output",
    "cache",
}
DEFAULTS = {
    "rerankers": ["none"],
    "zooms": [1.0],
    "overlaps": [0.0],
    "top_n": [20],
    "top_k": 1,
    "thresholds_m": [10.0, 25.0, 50.0, 100.0],
    "device": "auto",
}
NO_RERANKER = "none"


@dataclass(frozen=True)
class MapSpec:
    name: str
    path: Path
    tile_m: float | None = None
    local_turns: bool = False  # aeroloc build --local-turns: the tiles' local features at eight turns
    global_turns: bool = False  # aeroloc build --global-turns: the tiles' global descriptors at eight turns


@dataclass(frozen=True)
class QuerySpec:
    name: str
    path: Path
    map: str
    limit: int | None = None  # evenly spaced subset of this many queries
    north_up: bool = False  # images north-up within ±45°: the re-ranker skips its 90° rotation search
    query_gsd: float | None = (
        None  # metres per query pixel: the dense stage runs first (aeroloc.localization.dense_stage)
    )
    priors: str = "auto"  # aeroloc.core.queries.load_queries(priors=...): none, rough, exact or auto
    seed: int = 0  # of the "rough" priors' noise


@dataclass(frozen=True)
class Experiment:
    name: str
    file: Path
    maps: tuple[MapSpec, ...]
    queries: tuple[QuerySpec, ...]
    methods: tuple[str, ...]
    rerankers: tuple[str | None, ...]  # None = retrieval only
    zooms: tuple[float, ...]
    overlaps: tuple[float, ...]
    top_n: tuple[int, ...]
    top_k: int
    thresholds_m: tuple[float, ...]
    device: str
    output: Path
    cache: Path
    description: str = ""

    def map_spec(self, name: str) -> MapSpec:
        return next(m for m in self.maps if m.name == name)


@dataclass(frozen=True)
class Config:
    """One point of the sweep; the attribute names are what ``aeroloc.bench.pipeline.run_config`` reads."""

    experiment: str
    map_name: str
    map_path: str
    tile_m: float | None
    queries_name: str
    queries_path: str
    method: str
    reranker: str | None
    zoom: float
    overlap: float
    top_n: int
    top_k: int
    thresholds_m: tuple[float, ...]
    device: str
    map_identity: str = field(default="", compare=False)
    queries_identity: str = field(default="", compare=False)
    max_queries: int | None = None  # the pipeline keeps sample_queries(queries, max_queries)
    north_up: bool = False  # localize_queries(north_up=...)
    query_gsd: float | None = None  # localize_queries(query_gsd=...)
    priors: str = "auto"  # load_queries(priors=...)
    seed: int = 0
    local_turns: bool = False  # the database holds turned tiles (aeroloc.matching.features.build_local)
    global_turns: bool = False  # the database holds turned descriptors (aeroloc.retrieval.database.build_global)

    def key(self) -> str:
        """Stable across machines and runs: content identities of map and queries (not their paths or labels)
        plus every setting that changes the measurement."""
        from aeroloc.core.io import config_key

        parts = [
            self.map_identity or self.map_path,
            self.tile_m,
            self.queries_identity or self.queries_path,
            self.method,
            self.reranker,
            float(self.zoom),
            float(self.overlap),
            int(self.top_n),
            int(self.top_k),
            [float(t) for t in self.thresholds_m],
            self.device,
        ]
        if self.max_queries is not None:  # only when set, so keys of full query sets stay as they were
            parts.append({"max_queries": int(self.max_queries)})
        if self.north_up:  # likewise only when set
            parts.append({"north_up": True})
        if self.local_turns:  # likewise
            parts.append({"local_turns": True})
        if self.global_turns:  # likewise
            parts.append({"global_turns": True})
        if self.priors != "auto":  # likewise
            parts.append({"priors": self.priors, "seed": int(self.seed)})
        if self.query_gsd is not None:
            from aeroloc.matching.dense import heading_angles

            parts.append({"query_gsd": float(self.query_gsd), "dense": heading_angles(None, self.north_up)})
        if self.reranker:  # the re-ranker's effective settings: a changed default must not reuse old results
            from aeroloc.matching.registry import rerank_conf

            parts.append({"rerank_conf": rerank_conf(self.reranker)})
            # and the sweep's (it runs with a re-ranker to confirm its candidates), likewise
            from aeroloc.localization.options import LocalizeOptions

            parts.append({"sweep": LocalizeOptions().sweep_conf()})
        return config_key(*parts)

    def label(self) -> str:
        qs = self.queries_name if self.max_queries is None else f"{self.queries_name} ({self.max_queries} queries)"
        parts = [
            qs,
            self.method,
            self.reranker or "retrieval",
            f"zoom {self.zoom:g}",
            f"overlap {self.overlap:g}",
            f"N={self.top_n}",
        ]
        if self.reranker:
            parts.append(f"K={self.top_k}")
        if self.north_up:
            parts.append("north-up")
        if self.local_turns:
            parts.append("turned tiles")
        if self.global_turns:
            parts.append("turned descriptors")
        if self.query_gsd is not None:
            parts.append(f"dense @ {self.query_gsd:g} m/px")
        if self.priors != "auto":
            parts.append(f"priors {self.priors}")
        return " · ".join(parts)

    def as_dict(self) -> dict:
        d = asdict(self)
        d["thresholds_m"] = list(self.thresholds_m)
        return d


def project_root(yaml_path: Path) -> Path:
    """Where relative paths of ``yaml_path`` point from (see the module docstring)."""
    folder = yaml_path.resolve().parent
    for cand in (folder, *folder.parents):
        if (cand / "pyproject.toml").is_file() or (cand / ".git").exists():
            return cand
    return folder


def load_experiment(path) -> Experiment:
    """Read and validate an experiment YAML; every problem is an AerolocError naming the file and the field."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise AerolocError(f"{path}: experiment file not found")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        where = getattr(exc, "problem_mark", None)
        line = f" (line {where.line + 1})" if where is not None else ""
        raise AerolocError(f"{path}: not valid YAML{line}: {getattr(exc, 'problem', exc)}") from None
    if not isinstance(raw, dict):
        raise AerolocError(f"{path}: expected a mapping of fields (name, maps, queries, methods …)")
    return _Validator(path, raw).experiment()


class _Validator:
    def __init__(self, path: Path, raw: dict):
        self.path, self.raw = path, raw
        self.root = project_root(path)

    def fail(self, field_: str, problem: str):
        raise AerolocError(f"{self.path}: {field_}: {problem}")

    def experiment(self) -> Experiment:
        raw = self.raw
        unknown = sorted(set(map(str, raw)) - KEYS)
        if unknown:
            self.fail(unknown[0], f"unknown field (known: {', '.join(sorted(KEYS))})")
        for req in ("name", "maps", "queries", "methods"):
            if raw.get(req) in (None, "", []):
                self.fail(req, "is required")
        name = raw["name"]
        if not isinstance(name, str) or not name.strip():
            self.fail("name", f"expected a non-empty text, got {name!r}")
        maps = self.maps()
        queries = self.queries({m.name for m in maps})
        methods = tuple(self.names("methods", raw["methods"]))
        self.check_methods(methods)
        rerankers = self.rerankers()
        zooms = tuple(self.numbers("zooms", lambda v: v > 0, "must be > 0"))
        overlaps = tuple(self.numbers("overlaps", lambda v: 0 <= v < 1, "must be in [0, 1)"))
        top_n = tuple(self.integers("top_n"))
        top_k = self.integers("top_k")
        if len(top_k) != 1:
            self.fail("top_k", "expected one integer")
        if top_k[0] > min(top_n):
            self.fail("top_k", f"{top_k[0]} is larger than the smallest top_n ({min(top_n)})")
        thresholds = tuple(sorted(self.numbers("thresholds_m", lambda v: v > 0, "must be > 0 metres")))
        device = raw.get("device", DEFAULTS["device"])
        if not isinstance(device, str) or not device.strip():
            self.fail("device", f"expected a device name (auto, cpu, cuda, cuda:N, mps), got {device!r}")
        output = self.resolve("output", raw.get("output") or f"runs/{name}", must_exist=False)
        cache = self.resolve("cache", raw["cache"], must_exist=False) if raw.get("cache") else output / "cache"
        return Experiment(
            name=name.strip(),
            file=self.path.resolve(),
            maps=tuple(maps),
            queries=tuple(queries),
            methods=methods,
            rerankers=rerankers,
            zooms=zooms,
            overlaps=overlaps,
            top_n=top_n,
            top_k=top_k[0],
            thresholds_m=thresholds,
            device=device.strip(),
            output=output,
            cache=cache,
            description=str(raw.get("description") or ""),
        )

    # --- fields -----------------------------------------------------------------------------------------
    def maps(self) -> list[MapSpec]:
        out = []
        for i, m in enumerate(self.entries("maps")):
            where = f"maps[{i}]"
            self.only_keys(where, m, {"name", "path", "tile_m", "local_turns", "global_turns"})
            name = self.text(f"{where}.name", m.get("name"))
            tile_m = m.get("tile_m")
            if tile_m is not None and (not _is_number(tile_m) or not tile_m > 0):
                self.fail(f"{where}.tile_m", f"must be a positive number of metres (or left out), got {tile_m!r}")
            turns = [m.get(k, False) for k in ("local_turns", "global_turns")]
            for k, v in zip(("local_turns", "global_turns"), turns):
                if not isinstance(v, bool):
                    self.fail(f"{where}.{k}", f"expected true or false, got {v!r}")
            path = self.resolve(f"{where}.path", m.get("path"))
            out.append(MapSpec(name, path, None if tile_m is None else float(tile_m), *turns))
        self.unique("maps", [m.name for m in out])
        return out

    def queries(self, map_names: set[str]) -> list[QuerySpec]:
        out = []
        for i, q in enumerate(self.entries("queries")):
            where = f"queries[{i}]"
            self.only_keys(where, q, {"name", "path", "map", "limit", "north_up", "query_gsd", "priors", "seed"})
            priors, seed = q.get("priors", "auto"), q.get("seed", 0)
            if priors not in ("auto", "none", "rough", "exact"):
                self.fail(f"{where}.priors", f"expected none, rough, exact or auto, got {priors!r}")
            if isinstance(seed, bool) or not isinstance(seed, int):
                self.fail(f"{where}.seed", f"expected an integer, got {seed!r}")
            north_up = q.get("north_up", False)
            if not isinstance(north_up, bool):
                self.fail(f"{where}.north_up", f"expected true or false, got {north_up!r}")
            gsd = q.get("query_gsd")
            if gsd is not None:
                from aeroloc.localization.dense_stage import check_query_gsd

                try:
                    if isinstance(gsd, bool) or not isinstance(gsd, (int, float)):
                        raise AerolocError("not a number")
                    gsd = check_query_gsd(gsd)
                except AerolocError:
                    self.fail(f"{where}.query_gsd", f"expected metres per pixel > 0 (or left out), got {gsd!r}")
            limit = q.get("limit")
            if limit is not None and (isinstance(limit, bool) or not isinstance(limit, int) or limit < 1):
                self.fail(f"{where}.limit", f"expected a number of queries >= 1 (or left out), got {limit!r}")
            name = self.text(f"{where}.name", q.get("name"))
            map_name = q.get("map")
            if map_name is None and len(map_names) == 1:
                map_name = next(iter(map_names))
            if map_name not in map_names:
                self.fail(f"{where}.map", f"{map_name!r} is not one of the maps ({', '.join(sorted(map_names))})")
            path = self.resolve(f"{where}.path", q.get("path"))
            out.append(QuerySpec(name, path, map_name, limit, north_up, gsd, priors, seed))
        self.unique("queries", [q.name for q in out])
        return out

    def check_methods(self, methods):
        from aeroloc.retrieval.models import METHODS

        for i, m in enumerate(methods):
            if m not in METHODS:
                self.fail(f"methods[{i}]", f"unknown retrieval method {m!r} (known: {', '.join(sorted(METHODS))})")

    def rerankers(self) -> tuple[str | None, ...]:
        names = self.names("rerankers", self.raw.get("rerankers", DEFAULTS["rerankers"]))
        try:
            from aeroloc.matching.registry import RERANKERS
        except ImportError:  # registry not in this build: names are checked when the re-ranker is built
            RERANKERS = None
        out = []
        for i, r in enumerate(names):
            if r.lower() == NO_RERANKER:
                out.append(None)
            elif RERANKERS is not None and r not in RERANKERS:
                self.fail(f"rerankers[{i}]", f"unknown re-ranker {r!r} (known: none, {', '.join(sorted(RERANKERS))})")
            else:
                out.append(r)
        self.unique("rerankers", [r or NO_RERANKER for r in out])
        return tuple(out)

    # --- helpers ----------------------------------------------------------------------------------------
    def entries(self, field_: str) -> list[dict]:
        v = self.raw[field_]
        if isinstance(v, dict):
            v = [v]
        if not isinstance(v, list) or not all(isinstance(e, dict) for e in v):
            self.fail(field_, "expected a list of mappings (name, path …)")
        return v

    def only_keys(self, where: str, entry: dict, allowed: set[str]):
        extra = sorted(set(map(str, entry)) - allowed)
        if extra:
            self.fail(f"{where}.{extra[0]}", f"unknown field (known: {', '.join(sorted(allowed))})")

    def text(self, where: str, v) -> str:
        if not isinstance(v, str) or not v.strip():
            self.fail(where, f"expected a non-empty text, got {v!r}")
        return v.strip()

    def names(self, field_: str, v) -> list[str]:
        v = v if isinstance(v, list) else [v]
        if not v:
            self.fail(field_, "must list at least one name")
        for i, e in enumerate(v):
            if not isinstance(e, str) or not e.strip():
                self.fail(f"{field_}[{i}]", f"expected a name, got {e!r}")
        return [e.strip() for e in v]

    def numbers(self, field_: str, ok, rule: str) -> list[float]:
        v = self.raw.get(field_, DEFAULTS[field_])
        v = v if isinstance(v, list) else [v]
        if not v:
            self.fail(field_, "must list at least one value")
        out = []
        for i, e in enumerate(v):
            if not _is_number(e):
                self.fail(f"{field_}[{i}]", f"expected a number, got {e!r}")
            if not ok(e):
                self.fail(f"{field_}[{i}]", f"{e!r} {rule}")
            out.append(float(e))
        self.unique(field_, out)
        return out

    def integers(self, field_: str) -> list[int]:
        v = self.raw.get(field_, DEFAULTS[field_])
        v = v if isinstance(v, list) else [v]
        if not v:
            self.fail(field_, "must list at least one value")
        for i, e in enumerate(v):
            if isinstance(e, bool) or not isinstance(e, int) or e < 1:
                self.fail(f"{field_}[{i}]" if len(v) > 1 else field_, f"expected an integer >= 1, got {e!r}")
        self.unique(field_, v)
        return [int(e) for e in v]

    def unique(self, field_: str, values):
        seen = set()
        for v in values:
            if v in seen:
                self.fail(field_, f"{v!r} is listed twice")
            seen.add(v)

    def resolve(self, where: str, v, must_exist: bool = True) -> Path:
        if not isinstance(v, str) or not v.strip():
            self.fail(where, f"expected a path, got {v!r}")
        p = Path(os.path.expanduser(os.path.expandvars(v.strip())))
        if not p.is_absolute():
            p = self.root / p
        p = Path(os.path.normpath(p))
        if must_exist and not p.exists():
            self.fail(where, f"{p} not found (relative paths start at {self.root})")
        return p


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and v == v and abs(v) != float("inf")


def identity(path: Path) -> str:
    """Content identity of a map/queries file (size + head/tail digest) or folder (names and sizes)."""
    from aeroloc.core.io import file_identity

    path = Path(path)
    if path.is_file():
        return file_identity(path)
    h = hashlib.sha1()
    for dirpath, dirnames, filenames in sorted(os.walk(path)):
        dirnames.sort()
        for f in sorted(filenames):
            p = Path(dirpath, f)
            h.update(f"{p.relative_to(path)}:{p.stat().st_size};".encode())
    return h.hexdigest()[:16]


def sample_queries(queries: list, n: int | None) -> list:
    """``n`` evenly spaced items of ``queries`` in their order (all when ``n`` is None or >= len): query files
    are often sorted by date or camera, so a prefix would test one season only."""
    if n is None or n >= len(queries):
        return list(queries)
    return [queries[(i * len(queries)) // n] for i in range(n)]


def expand(exp: Experiment) -> list[Config]:
    """The sweep grid, ordered so configurations sharing a tile database (map, zoom, overlap) run together."""
    ids: dict[Path, str] = {}

    def ident(p: Path) -> str:
        if p not in ids:
            ids[p] = identity(p)
        return ids[p]

    out, keys = [], set()
    for q in exp.queries:
        m = exp.map_spec(q.map)
        for method, zoom, overlap, reranker in itertools.product(exp.methods, exp.zooms, exp.overlaps, exp.rerankers):
            for n in exp.top_n if reranker else (max(exp.top_n),):
                c = Config(
                    experiment=exp.name,
                    map_name=m.name,
                    map_path=str(m.path),
                    tile_m=m.tile_m,
                    local_turns=m.local_turns and bool(reranker),  # retrieval alone reads no local features
                    global_turns=m.global_turns,
                    queries_name=q.name,
                    queries_path=str(q.path),
                    method=method,
                    reranker=reranker,
                    zoom=zoom,
                    overlap=overlap,
                    top_n=n,
                    top_k=min(exp.top_k, n),
                    thresholds_m=exp.thresholds_m,
                    device=exp.device,
                    map_identity=ident(m.path),
                    queries_identity=ident(q.path),
                    max_queries=q.limit,
                    north_up=q.north_up and reranker is not None,  # retrieval ignores both
                    query_gsd=q.query_gsd if reranker is not None else None,
                    priors=q.priors,
                    seed=q.seed,
                )
                if c.key() not in keys:  # e.g. one queries file listed under two names: measure it once
                    keys.add(c.key())
                    out.append(c)
    return out
