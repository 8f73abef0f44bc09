"""The one-page public API (``from aeroloc import ...``): every name resolves, and the README's five lines work
on a real map and a real cross-season query."""

import math

import pytest

import aeroloc
from aeroloc.core import geo


def test_every_exported_name_resolves_to_its_stage_module():
    for name in aeroloc.__all__:
        obj = getattr(aeroloc, name)
        assert obj is not None, name
        if name != "__version__" and hasattr(obj, "__module__"):
            assert obj.__module__.startswith("aeroloc."), (name, obj.__module__)
    with pytest.raises(AttributeError, match="no attribute 'Nope'"):
        aeroloc.Nope  # noqa: B018


@pytest.mark.slow
def test_the_readme_five_lines_localize_a_cross_season_query(naip_map, naip_dev, tmp_path):
    from aeroloc import LocalizeOptions, Localizer, build_database, load_queries, read_image

    q = {q.name: q for q in load_queries(naip_dev)}["naip_20120731_n_018.jpg"]
    db = build_database(naip_map, tmp_path / "db", tile_m=1280, method="xfeat-vlad", device="cpu")
    localizer = Localizer(db, LocalizeOptions(north_up=True, method="xfeat-vlad"), "cpu")
    fix = localizer(q.name, read_image(q.path))
    assert fix.status == "localized" and fix.localized, fix.status
    assert geo.geodesic_distance(q.lat, q.lon, fix.lat, fix.lon) < 25.0
    again = build_database(naip_map, tmp_path / "db", tile_m=1280, method="xfeat-vlad", device="cpu")
    assert again.folder == db.folder and len(again.tiles) == len(db.tiles)  # cached: the same database
    elsewhere = localizer("mirrored", read_image(q.path)[:, ::-1].copy())
    assert not elsewhere.localized and math.isnan(elsewhere.lat) and elsewhere.status.startswith("not localized")
