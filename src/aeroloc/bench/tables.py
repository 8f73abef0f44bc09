"""The paper's tables from result rows (``ResultStore.results()``), as Markdown, LaTeX (booktabs) and HTML.

One table per query set and layout:
- zoom / overlap: rows = methods, columns = zoom (overlap) values × retrieval R@1/R@5/R@10, plus the best
  zoom (overlap) by R@1 (ties broken by R@5, R@10). Bold: per row, the best of each R@N across the sweep.
- re-ranking: rows = method × re-ranker, per N: R@1 before (retrieval) and after re-ranking, and the re-ranking
  cost in ms/query. Bold: the best R@1 of the row.
- georeference, time, memory: rows = configurations; bold = the best of each *column* (highest recall, lowest
  error/time/bytes), since the numbers in one row measure different things.
Recalls are percentages; "–" = not measured. Values are compared as displayed, so equal displays tie in bold; a row/column whose values are all equal
has no bold.
"""

from __future__ import annotations

import html
import math
import re
from dataclasses import dataclass, field

RECALL_NS = (1, 5, 10)
STAGES = ("descriptor", "search", "local_features", "rerank", "align")
STAGE_NAMES = {
    "descriptor": "descriptor",
    "search": "search",
    "local_features": "local features",
    "rerank": "re-rank",
    "sweep": "sweep",
    "align": "align",
}
LABEL_FIELDS = (
    ("method", "Method"),
    ("reranker", "Re-ranker"),
    ("zoom", "Zoom"),
    ("overlap", "Overlap"),
    ("top_n", "N"),
    ("top_k", "K"),
    ("tile_m", "Tile m"),
)


@dataclass
class Cell:
    value: float | str | None
    digits: int = 1
    bold: bool = False

    @property
    def text(self) -> str:
        v = self.value
        if v is None or (isinstance(v, float) and not math.isfinite(v)):
            return "–"
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            return f"{v:.{self.digits}f}"
        return str(v)

    @property
    def number(self) -> float | None:
        """The value as displayed (so ties in print are ties in bold), or None for text/missing."""
        v = self.value
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            return None
        return round(float(v), self.digits)


@dataclass
class Table:
    key: str  # zoom, overlap, rerank, georef, time, memory
    title: str
    labels: list[str]  # headers of the label columns
    columns: list[str]  # headers of the value columns
    rows: list[list[Cell]]  # label cells then value cells
    groups: list[tuple[str, int]] = field(default_factory=list)  # spanning header over the value columns
    note: str = ""
    dataset: str = ""

    def headers(self, flat: bool) -> list[str]:
        if not flat or not self.groups:
            return self.labels + self.columns
        out, i = list(self.labels), 0
        for name, span in self.groups:
            out += [f"{name} {c}".strip() for c in self.columns[i : i + span]]
            i += span
        return out

    def markdown(self) -> str:
        heads = self.headers(flat=True)
        lines = [
            f"**{self.title}**",
            "",
            "| " + " | ".join(heads) + " |",
            "|" + "|".join(":---" if i < len(self.labels) else "---:" for i in range(len(heads))) + "|",
        ]
        for row in self.rows:
            lines.append("| " + " | ".join(f"**{c.text}**" if c.bold else c.text for c in row) + " |")
        if self.note:
            lines += ["", f"*{self.note}*"]
        return "\n".join(lines)

    def latex(self) -> str:
        spec = "l" * len(self.labels) + "r" * len(self.columns)
        out = [
            "\\begin{table}[t]",
            "\\centering",
            f"\\caption{{{_tex(self.title)}}}",
            f"\\begin{{tabular}}{{{spec}}}",
            "\\toprule",
        ]
        if self.groups:
            cells, rules, col = [""] * len(self.labels), [], len(self.labels) + 1
            for name, span in self.groups:
                cells.append(f"\\multicolumn{{{span}}}{{c}}{{{_tex(name)}}}" if span > 1 else _tex(name))
                if name:
                    rules.append(f"\\cmidrule(lr){{{col}-{col + span - 1}}}")
                col += span
            out += [" & ".join(cells) + " \\\\", " ".join(rules)]
        out.append(" & ".join(_tex(h) for h in self.labels + self.columns) + " \\\\")
        out.append("\\midrule")
        for row in self.rows:
            out.append(" & ".join(f"\\textbf{{{_tex(c.text)}}}" if c.bold else _tex(c.text) for c in row) + " \\\\")
        out += ["\\bottomrule", "\\end{tabular}"]
        if self.note:
            out.append(f"\\par\\smallskip{{\\footnotesize {_tex(self.note)}}}")
        out.append("\\end{table}")
        return "\n".join(out)

    def html(self) -> str:
        e = html.escape
        head = []
        if self.groups:
            head.append(
                "<tr>"
                + "".join(f"<th rowspan=2>{e(h)}</th>" for h in self.labels)
                + "".join(f"<th colspan={s} class=grp>{e(n)}</th>" for n, s in self.groups)
                + "</tr>"
            )
            head.append("<tr>" + "".join(f"<th>{e(c)}</th>" for c in self.columns) + "</tr>")
        else:
            head.append("<tr>" + "".join(f"<th>{e(h)}</th>" for h in self.labels + self.columns) + "</tr>")
        body = []
        for row in self.rows:
            tds = []
            for i, c in enumerate(row):
                cls = "lab" if i < len(self.labels) else "num"
                txt = f"<b>{e(c.text)}</b>" if c.bold else e(c.text)
                tds.append(f"<td class={cls}>{txt}</td>")
            body.append("<tr>" + "".join(tds) + "</tr>")
        note = f"<p class=note>{e(self.note)}</p>" if self.note else ""
        return (
            f"<figure class=table id=table-{e(self.key)}><figcaption>{e(self.title)}</figcaption>"
            f"<table><thead>{''.join(head)}</thead><tbody>{''.join(body)}</tbody></table>{note}</figure>"
        )


_TEX = {
    "\\": r"\textbackslash{}",
    "&": r"\&",
    "%": r"\%",
    "$": r"\$",
    "#": r"\#",
    "_": r"\_",
    "{": r"\{",
    "}": r"\}",
    "~": r"\textasciitilde{}",
    "^": r"\textasciicircum{}",
    "–": "--",
    "—": "---",
    "×": r"$\times$",
    "·": r"$\cdot$",
    "≤": r"$\leq$",
    "Δ": r"$\Delta$",
}


def _tex(s: str) -> str:
    return "".join(_TEX.get(ch, ch) for ch in str(s))


def mark_best(cells: list[Cell], higher: bool = True) -> None:
    """Bold every cell whose displayed number is the best of ``cells`` (ties all bold); nothing when all
    displayed numbers are equal, since then no value stands out."""
    nums = [c.number for c in cells if c.number is not None]
    if len(set(nums)) < 2:
        return
    best = max(nums) if higher else min(nums)
    for c in cells:
        if c.number is not None and c.number == best:
            c.bold = True


# --- helpers over result rows ---------------------------------------------------------------------------
def pct(v) -> float | None:
    return None if v is None else 100.0 * float(v)


def retrieval_recall(row: dict, n: int) -> float | None:
    """Recall@N of the retrieval stage (before re-ranking): the pipeline's ``retrieval_vpr_recall@N``, or
    ``vpr_recall@N`` for rows that only carry the latter."""
    v = row.get(f"retrieval_vpr_recall@{n}")
    return row.get(f"vpr_recall@{n}") if v is None else v


def label_value(row: dict, f: str) -> str:
    v = row.get(f)
    if f == "reranker":
        return v or "none"
    if isinstance(v, float):
        return f"{v:g}"
    return "–" if v is None else str(v)


def describe(row: dict, fields) -> str:
    """Short label of a configuration: method and re-ranker by name, other fields as "zoom 1", "N 20"."""
    return " · ".join(
        label_value(row, f) if f in ("method", "reranker") else f"{name.lower()} {label_value(row, f)}"
        for f, name in fields
    )


def varying(rows: list[dict], exclude=(), always=("method",)) -> list[tuple[str, str]]:
    """The label fields that differ between ``rows`` (and the ``always`` ones), in a fixed order."""
    out = []
    for f, name in LABEL_FIELDS:
        if f in exclude:
            continue
        if f in always or len({label_value(r, f) for r in rows}) > 1:
            out.append((f, name))
    return out


def by_dataset(rows: list[dict]) -> dict[str, list[dict]]:
    out: dict[str, list[dict]] = {}
    for r in rows:
        out.setdefault(r["queries"], []).append(r)
    return out


def _num(v) -> float | None:
    return None if v is None or (isinstance(v, float) and not math.isfinite(v)) else float(v)


# --- layouts ---------------------------------------------------------------------------------------------
def sweep_table(rows: list[dict], axis: str, dataset: str) -> Table | None:
    """Retrieval recall by ``axis`` ("zoom" or "overlap"); None when rows hold a single axis value only."""
    values = sorted({float(r[axis]) for r in rows})
    if len(values) < 2:
        return None
    # one retrieval measurement per (identity, axis value); a retrieval-only row is preferred, and the
    # re-ranker/N/K do not change retrieval, so they are not part of the identity
    labels = varying(rows, exclude=(axis, "reranker", "top_n", "top_k"))
    groups: dict[tuple, dict[float, dict]] = {}
    for r in sorted(rows, key=lambda r: (r.get("reranker") is None, r.get("top_n") or 0)):
        ident = tuple(label_value(r, f) for f, _ in labels)
        groups.setdefault(ident, {})[float(r[axis])] = r
    name = "Zoom" if axis == "zoom" else "Overlap"
    out_rows = []
    for ident, per_value in groups.items():
        cells = [Cell(v) for v in ident]
        value_cells = {n: [] for n in RECALL_NS}
        for v in values:
            r = per_value.get(v)
            for n in RECALL_NS:
                c = Cell(pct(retrieval_recall(r, n)) if r else None)
                value_cells[n].append(c)
                cells.append(c)
        for n in RECALL_NS:
            mark_best(value_cells[n])
        scored = [
            (tuple(value_cells[n][i].number if value_cells[n][i].number is not None else -1 for n in RECALL_NS), v)
            for i, v in enumerate(values)
        ]
        best = max(scored, key=lambda s: s[0]) if scored else None
        cells.append(Cell(f"{best[1]:g}" if best and best[0][0] >= 0 else None))
        out_rows.append(cells)
    groups_hdr = [(f"{name.lower()} {v:g}", len(RECALL_NS)) for v in values] + [("", 1)]
    columns = [f"R@{n}" for _ in values for n in RECALL_NS] + [f"best {name.lower()}"]
    return Table(
        axis,
        f"VPR Recall (%) by {name.lower()} — {dataset}",
        [n for _, n in labels],
        columns,
        out_rows,
        groups_hdr,
        note=f"Retrieval only (before re-ranking). Bold: best {name.lower()} per row and R@N.",
    )


def rerank_table(rows: list[dict], dataset: str) -> Table | None:
    rr = [r for r in rows if r.get("reranker")]
    if not rr:
        return None
    ns = sorted({int(r["top_n"]) for r in rr})
    labels = varying(rr, exclude=("top_n",), always=("method", "reranker"))
    groups: dict[tuple, dict[int, dict]] = {}
    for r in rr:
        groups.setdefault(tuple(label_value(r, f) for f, _ in labels), {})[int(r["top_n"])] = r
    out_rows = []
    for ident, per_n in groups.items():
        cells, recalls = [Cell(v) for v in ident], []
        for n in ns:
            r = per_n.get(n)
            before = Cell(pct(r.get("retrieval_vpr_recall@1")) if r else None)
            after = Cell(pct(r.get("vpr_recall@1")) if r else None)
            cost = Cell(_num(sum(r.get(f"{s}_ms") or 0 for s in ("local_features", "rerank"))) if r else None, 0)
            cells += [before, after, cost]
            recalls += [before, after]
        mark_best(recalls)
        out_rows.append(cells)
    return Table(
        "rerank",
        f"VPR Recall@1 (%) before and after re-ranking — {dataset}",
        [n for _, n in labels],
        ["R@1 before", "R@1 after", "ms/query"] * len(ns),
        out_rows,
        [(f"N = {n}", 3) for n in ns],
        note="before = retrieval ranking, after = re-ranked by verified inliers; ms/query = local features "
        "+ matching. Bold: best R@1 of the row.",
    )


def georef_table(rows: list[dict], dataset: str, thresholds=None) -> Table | None:
    if not rows:
        return None
    if thresholds is None:
        thresholds = sorted(
            {float(k[len("georef_recall@") : -1]) for r in rows for k in r if re.fullmatch(r"georef_recall@[\d.]+m", k)}
        )
    labels = varying(rows, always=("method", "reranker"))
    cols, out_rows = [], []
    columns = [f"≤{t:g} m" for t in thresholds] + ["median m", "p90 m", "not loc. %"]
    for r in rows:
        vals = [Cell(pct(r.get(f"georef_recall@{t:g}m"))) for t in thresholds]
        vals += [
            Cell(_num(r.get("median_error_m"))),
            Cell(_num(r.get("p90_error_m"))),
            Cell(pct(r.get("not_localized"))),
        ]
        out_rows.append([Cell(label_value(r, f)) for f, _ in labels] + vals)
        cols.append(vals)
    for j in range(len(columns)):
        mark_best([c[j] for c in cols], higher=j < len(thresholds))
    return Table(
        "georef",
        f"Georeference Recall (%) and error — {dataset}",
        [n for _, n in labels],
        columns,
        out_rows,
        [("Georeference Recall", len(thresholds)), ("error", 3)],
        note="Recall = estimate within d metres of the truth (not localized = miss); errors over localized "
        "queries. Re-ranker none = centre of the top tile. Bold: best per column.",
    )


def atlas_table(rows: list[dict]) -> Table | None:
    """Every query set x prior mode in one table: Georef@t (t = max(5 m, 2 map px)), not localized, wrong
    (> max(25 m, 10 map px)), median s/query — the any-terrain benchmark (experiments/atlas.yaml)."""
    rows = [r for r in rows if r.get("georef_recall@t") is not None]
    if not rows:
        return None
    out_rows = []
    for r in sorted(rows, key=lambda r: (r.get("queries") or "", r.get("priors") or "")):
        out_rows.append(
            [
                Cell(str(r.get("queries"))),
                Cell(str(r.get("priors") or "auto")),
                Cell(pct(r.get("georef_recall@t"))),
                Cell(_num(r.get("t_m")), 1),
                Cell(pct(r.get("not_localized"))),
                Cell(_num(r.get("wrong_n")), 0),
                Cell(_num((r.get("median_ms_per_query") or 0) / 1000), 2),
            ]
        )
    return Table(
        "atlas",
        "Any terrain: every query set and prior mode",
        ["query set", "priors"],
        ["Georef@t %", "t m", "not loc. %", "wrong", "s/query (median)"],
        out_rows,
        note="t = max(5 m, 2 map px); wrong = localized farther than max(25 m, 10 map px); priors: none = no "
        "heading or ground resolution, rough = truth with sensor-like noise (ground resolution x U(0.8, 1.25), "
        "heading ± 15°), exact = truth.",
    )


def time_table(rows: list[dict], dataset: str) -> Table | None:
    if not rows:
        return None
    labels = varying(rows, always=("method", "reranker"))
    columns = [STAGE_NAMES[s] for s in STAGES] + ["total ms/query", "total s"]
    cols, out_rows = [], []
    for r in rows:
        vals = []
        for s in STAGES:
            v = _num(r.get(f"{s}_ms"))
            if not r.get("reranker") and s in ("local_features", "rerank", "align") and not v:
                v = None  # stage not part of a retrieval-only configuration
            vals.append(Cell(v))
        total = _num(r.get("total_ms_per_query"))
        if total is None:
            total = sum(c.value for c in vals if c.value is not None)
        vals += [Cell(total), Cell(_num(r.get("localize_total_s")))]
        out_rows.append([Cell(label_value(r, f)) for f, _ in labels] + vals)
        cols.append(vals)
    for j in range(len(columns)):
        mark_best([c[j] for c in cols], higher=False)
    return Table(
        "time",
        f"Time per stage (ms per query) — {dataset}",
        [n for _, n in labels],
        columns,
        out_rows,
        note="Same clock (perf_counter) for every stage; total s = the queries' totals summed (database "
        "build excluded). Bold: fastest per column.",
    )


def memory_table(rows: list[dict], dataset: str) -> Table | None:
    if not rows:
        return None
    labels = varying(rows, exclude=("top_n", "top_k"), always=("method", "reranker"))
    seen, cols, out_rows = set(), [], []
    for r in rows:
        ident = tuple(label_value(r, f) for f, _ in labels)
        if ident in seen:
            continue
        seen.add(ident)
        kb = lambda v: None if _num(v) is None else _num(v) / 1024  # noqa: E731
        local = kb(r.get("local_bytes_per_tile")) if r.get("reranker") else None
        vals = [
            Cell(kb(r.get("descriptor_bytes_per_tile"))),
            Cell(local),
            Cell(kb(r.get("index_bytes")), 0),
            Cell(_num(r.get("peak_rss_mb")), 0),
        ]
        out_rows.append([Cell(label_value(r, f)) for f, _ in labels] + [Cell(r.get("n_tiles"), 0)] + vals)
        cols.append(vals)
    for j in range(4):
        mark_best([c[j] for c in cols], higher=False)
    return Table(
        "memory",
        f"Memory — {dataset}",
        [n for _, n in labels],
        ["tiles", "descriptor KB/tile", "local KB/tile", "index KB", "peak RSS MB"],
        out_rows,
        note="Bytes on disk; peak RSS is the benchmark process's maximum so far (it only grows within a run). "
        "Bold: smallest per column.",
    )


def build_tables(rows: list[dict]) -> list[Table]:
    """Every layout that the rows can fill, per query set, in the paper's order."""
    out = []
    for dataset, rs in by_dataset(rows).items():
        for t in (
            sweep_table(rs, "zoom", dataset),
            sweep_table(rs, "overlap", dataset),
            rerank_table(rs, dataset),
            georef_table(rs, dataset),
            time_table(rs, dataset),
            memory_table(rs, dataset),
        ):
            if t is not None:
                t.dataset = dataset
                out.append(t)
    atlas = atlas_table(rows)
    if atlas is not None:
        atlas.dataset = "all"
        out.append(atlas)
    return out


def markdown(tables: list[Table]) -> str:
    return "\n\n".join(t.markdown() for t in tables) + "\n"


def latex(tables: list[Table]) -> str:
    head = "% generated by aeroloc bench; needs \\usepackage{booktabs}\n"
    return head + "\n\n".join(t.latex() for t in tables) + "\n"
