"""Benchmark plots as PNG files (matplotlib's Agg canvas directly: no pyplot state, no display needed).

- recall vs zoom / overlap: one panel per R@N, one line per method (retrieval ranking);
- error CDF: share of queries localized within x metres, one curve per configuration (not localized queries
  count in the denominator, so a curve tops out at the share localized);
- time per stage: stacked horizontal bars, ms per query, one bar per configuration.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from aeroloc.bench.tables import (
    RECALL_NS,
    STAGE_NAMES,
    STAGES,
    by_dataset,
    describe,
    label_value,
    retrieval_recall,
    varying,
)

COLOURS = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#7f7f7f", "#bcbd22"]
STAGE_COLOURS = ["#4c72b0", "#55a868", "#c44e52", "#8172b2", "#da8bc3", "#ccb974"]


@dataclass
class Plot:
    key: str
    title: str
    path: Path
    dataset: str = ""


def _figure(w: float, h: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png")
    return path


def _slug(s: str) -> str:
    return "".join(ch if ch.isalnum() else "-" for ch in s).strip("-").lower()


def series_label(row: dict, fields) -> str:
    return describe(row, fields) or label_value(row, "method")


def recall_vs(rows: list[dict], axis: str, dataset: str, path: Path) -> Path | None:
    """Retrieval R@1/5/10 against ``axis`` ("zoom"/"overlap"), a line per method (and other varying field)."""
    values = sorted({float(r[axis]) for r in rows})
    if len(values) < 2:
        return None
    fields = varying(rows, exclude=(axis, "reranker", "top_n", "top_k"))
    series: dict[str, dict[float, dict]] = {}
    for r in sorted(rows, key=lambda r: (r.get("reranker") is None, r.get("top_n") or 0)):
        series.setdefault(series_label(r, fields), {})[float(r[axis])] = r
    fig = _figure(3.4 * len(RECALL_NS), 3.2)
    axes = fig.subplots(1, len(RECALL_NS), sharey=True)
    for ax, n in zip(axes, RECALL_NS):
        for i, (label, per_value) in enumerate(series.items()):
            xs = [v for v in values if v in per_value and retrieval_recall(per_value[v], n) is not None]
            ys = [100 * retrieval_recall(per_value[v], n) for v in xs]
            ax.plot(xs, ys, "o-", color=COLOURS[i % len(COLOURS)], label=label, lw=2)
        ax.set_title(f"R@{n}")
        ax.set_xlabel(axis)
        ax.set_xticks(values)
        ax.set_ylim(0, 102)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("VPR Recall (%)")
    axes[-1].legend(fontsize=8, loc="lower right")
    fig.suptitle(f"Retrieval recall vs {axis} — {dataset}", fontsize=11)
    return _save(fig, path)


def error_cdf(curves: list[tuple[str, list[float | None]]], dataset: str, path: Path, thresholds=()) -> Path | None:
    """``curves``: (label, per-query errors in metres, None = not localized)."""
    curves = [(label, errs) for label, errs in curves if errs]
    if not curves:
        return None
    fig = _figure(9.0, 4.2)
    ax = fig.subplots()
    finite_all = [e for _, errs in curves for e in errs if e is not None and math.isfinite(e)]
    lo = max(0.1, min(min(finite_all, default=1.0) * 0.8, min(thresholds, default=1e9) * 0.5))
    hi = max(max(finite_all, default=10.0) * 1.2, max(thresholds, default=10.0) * 1.5, lo * 10)
    for i, (label, errs) in enumerate(curves):
        n = len(errs)
        finite = sorted(e for e in errs if e is not None and math.isfinite(e))
        xs = [lo] + [max(e, lo) for e in finite] + [hi]
        ys = [0.0] + [100 * (k + 1) / n for k in range(len(finite))] + [100 * len(finite) / n]
        ax.step(xs, ys, where="post", color=COLOURS[i % len(COLOURS)], lw=2, label=label)
    for t in thresholds:
        ax.axvline(t, color="#888", ls=":", lw=1)
        ax.text(t, 101, f"{t:g} m", ha="center", va="bottom", fontsize=7, color="#555")
    ax.set_xscale("log")
    ax.set_xlim(lo, hi)
    ax.set_ylim(0, 108)
    ax.set_xlabel("localization error (m, log scale)")
    ax.set_ylabel("queries within error (%)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    ax.set_title(f"Error CDF — {dataset}", fontsize=11)
    return _save(fig, path)


def time_bars(rows: list[dict], dataset: str, path: Path) -> Path | None:
    if not rows:
        return None
    fields = varying(rows, always=("method", "reranker"))
    labels = [series_label(r, fields) for r in rows]
    fig = _figure(8.0, 1.2 + 0.42 * len(rows))
    ax = fig.subplots()
    left = [0.0] * len(rows)
    for s, colour in zip(STAGES, STAGE_COLOURS):
        vals = [float(r.get(f"{s}_ms") or 0.0) for r in rows]
        ax.barh(range(len(rows)), vals, left=left, color=colour, label=STAGE_NAMES[s], height=0.6)
        left = [a + b for a, b in zip(left, vals)]
    for i, total in enumerate(left):
        ax.text(total, i, f" {total:.0f}", va="center", fontsize=8)
    ax.set_yticks(range(len(rows)), labels, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlim(0, max([*left, 1.0]) * 1.15)
    ax.set_xlabel("ms per query")
    ax.legend(fontsize=8, ncols=len(STAGES), loc="lower center", bbox_to_anchor=(0.5, 1.0), frameon=False)
    ax.grid(alpha=0.3, axis="x")
    ax.set_title(f"Time per stage — {dataset}", fontsize=11, pad=24)
    return _save(fig, path)


def make_plots(rows: list[dict], errors_by_key: dict[str, list[float | None]], folder, thresholds=()) -> list[Plot]:
    """Every plot the rows can fill, per query set. ``errors_by_key``: config key -> per-query errors."""
    folder = Path(folder)
    out = []
    for dataset, rs in by_dataset(rows).items():
        slug = _slug(dataset)
        for axis in ("zoom", "overlap"):
            p = recall_vs(rs, axis, dataset, folder / f"{slug}-recall-vs-{axis}.png")
            if p:
                out.append(Plot(f"recall-{axis}", f"Recall vs {axis}", p, dataset))
        fields = varying(rs, always=("method", "reranker"))
        curves = [(series_label(r, fields), errors_by_key.get(r["config_key"]) or []) for r in rs]
        p = error_cdf(curves, dataset, folder / f"{slug}-error-cdf.png", thresholds)
        if p:
            out.append(Plot("error-cdf", "Error CDF", p, dataset))
        p = time_bars(rs, dataset, folder / f"{slug}-time.png")
        if p:
            out.append(Plot("time", "Time per stage", p, dataset))
    return out
