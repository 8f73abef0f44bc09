"""Localize a query set into a results CSV: streamed, resumable, reused when asked for again.

One row per query is written as it finishes (:class:`aeroloc.core.io.ResumableCSV`), so an interrupted run
resumes where it stopped (same options and database) and nothing finished is lost; the final file appears by
rename. The same run asked for twice reads the finished file back.
"""

from __future__ import annotations

from aeroloc.core.errors import AerolocError, QueryImageError
from aeroloc.core.images import read_image
from aeroloc.core.io import ResumableCSV
from aeroloc.localization.localizer import Localizer
from aeroloc.localization.options import LocalizeOptions
from aeroloc.localization.results import COLUMNS, Localization
from aeroloc.retrieval.retriever import QUERY_SCALE


def localize_queries(
    db,
    queries,
    out_csv,
    options: LocalizeOptions | None = None,
    device="cpu",
    save_matches=None,
    progress: bool = True,
) -> list[Localization]:
    """Localize every query (aeroloc.core.queries.Query) of ``queries`` with ``options`` into ``out_csv``;
    returns the results in query order, as read back from the file (a fresh, resumed or reused run gives equal
    results). ``save_matches``: a folder for match pictures (aeroloc.localization.visualize)."""
    from tqdm import tqdm

    options = options or LocalizeOptions()
    priors = [q.priors.describe() for q in queries] if any(_known(q) for q in queries) else None
    sink = ResumableCSV(out_csv, COLUMNS, options.signature(db, [q.name for q in queries], QUERY_SCALE, priors))
    finished = sink.finished()
    if finished is not None:
        return [Localization.from_row(r) for r in finished]
    rows = sink.start()
    done = {r["name"] for r in rows}
    try:
        localizer = Localizer(db, options, device)
        todo = [q for q in queries if q.name not in done]
        for q in tqdm(todo, desc="localize", unit="query", disable=not progress, leave=False, dynamic_ncols=True):
            row = _localize_one(localizer, q, save_matches).row()
            sink.write(row)
            rows.append(row)
    except BaseException:
        sink.close()
        raise
    sink.finish()
    return [Localization.from_row(r) for r in rows]


def _localize_one(localizer: Localizer, q, save_matches) -> Localization:
    """One query's result; an unreadable image, or one a stage rejects as input (``QueryImageError``), is "not
    localized" with the reason, not an error for the run: a resumed run would meet the same query again and stop
    there again. The other errors (the database's, the map's) still end the run."""
    try:
        image = read_image(q.path)
    except AerolocError as exc:
        return Localization(q.name, status=f"not localized: {exc}")
    try:
        res = localizer(q.name, image, priors=getattr(q, "priors", None))
    except QueryImageError as exc:
        return Localization(q.name, status=f"not localized: {exc}")
    if save_matches:
        from aeroloc.localization.visualize import save_result_image

        save_result_image(save_matches, image, res, localizer.db, localizer.dense)
    return res


def _known(q) -> bool:
    p = getattr(q, "priors", None)
    return p is not None and p.known
