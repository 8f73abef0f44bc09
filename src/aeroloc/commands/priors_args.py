"""Command-line flags for per-query priors (heading, ground resolution), shared by the commands that localize.

A command calls :func:`add_prior_arguments` on its parser and, in ``run``, ``apply_overrides(queries,
priors_from_args(args))`` (:mod:`aeroloc.core.priors`) after :func:`aeroloc.core.queries.load_queries`. Flag values
are parsed there, so a bad one is an :class:`AerolocError` naming the flag (one line, exit 2), like a bad CSV cell.
Not a sub-command: ``aeroloc.cli`` lists its commands by name.
"""

from __future__ import annotations

from aeroloc.core.priors import (
    DEFAULT_GSD_TOL,
    DEFAULT_HEADING_TOL_DEG,
    ROUGH_GSD_FACTOR,
    ROUGH_HEADING_DEG,
    PriorOverrides,
)

# flag -> (PriorOverrides field, metavar, help)
_VALUE_FLAGS = {
    "--gsd": (
        "gsd_m",
        "M",
        "ground size of a query pixel in metres, for every query (replaces the file's gsd_m, alt_agl_m and camera)",
    ),
    "--gsd-tol": (
        "gsd_tol",
        "F",
        f"relative tolerance of the ground resolution, in (0, 1) (default {DEFAULT_GSD_TOL:g})",
    ),
    "--alt-agl": (
        "alt_agl_m",
        "M",
        "height above GROUND in metres (not GPS altitude above sea level): with --hfov, or --focal-mm and "
        "--sensor-w-mm, or the photos' EXIF field of view, gives the ground resolution",
    ),
    "--hfov": ("hfov_deg", "DEG", "camera's horizontal field of view in degrees, in (0, 180)"),
    "--focal-mm": ("focal_mm", "MM", "focal length in mm (with --sensor-w-mm)"),
    "--sensor-w-mm": ("sensor_w_mm", "MM", "sensor width in mm (with --focal-mm)"),
    "--heading": ("heading_deg", "DEG", "where the top of every image points, degrees clockwise from north"),
    "--heading-tol": (
        "heading_tol_deg",
        "DEG",
        f"heading tolerance in degrees, in [0, 180] (default {DEFAULT_HEADING_TOL_DEG:g}; 180 = any heading)",
    ),
}


def _dest(flag: str) -> str:
    return "prior_" + flag.lstrip("-").replace("-", "_")


def add_prior_arguments(parser) -> None:
    """The prior flags, in their own help group. Values stay text until :func:`priors_from_args`."""
    g = parser.add_argument_group(
        "priors",
        "what the aircraft knows, for every query; each flag overrides the query file's column (and EXIF). "
        "Unknown = searched. The file's columns: gsd_m, gsd_tol, alt_agl_m, hfov_deg, focal_mm, sensor_w_mm, "
        "heading_deg, heading_tol_deg (a generated set's heading_deg/gsd_m are truth, not priors)",
    )
    for flag, (_, metavar, help_) in _VALUE_FLAGS.items():
        g.add_argument(flag, dest=_dest(flag), metavar=metavar, help=help_)
    ex = g.add_mutually_exclusive_group()
    ex.add_argument(
        "--no-priors",
        dest="prior_none",
        action="store_true",
        help="ignore every prior of the query file and EXIF (the flags above still apply)",
    )
    ex.add_argument(
        "--priors-from-truth",
        dest="prior_from_truth",
        action="store_true",
        help="benchmarks: the set's true heading and ground resolution as priors (with --perturb-priors: rough ones)",
    )
    lo, hi = ROUGH_GSD_FACTOR
    g.add_argument(
        "--perturb-priors",
        dest="prior_perturb_seed",
        metavar="SEED",
        help=f"benchmarks: real-sensor-like noise on the priors, the same for a query and SEED on every run: "
        f"ground resolution x U({lo:g}, {hi:g}), heading + U(-{ROUGH_HEADING_DEG:g}, {ROUGH_HEADING_DEG:g})°",
    )


def priors_from_args(args) -> PriorOverrides:
    """The parsed flags of :func:`add_prior_arguments` (absent attributes count as not given); a bad value is an
    :class:`AerolocError` naming its flag."""
    values = {field: getattr(args, _dest(flag), None) for flag, (field, _, _) in _VALUE_FLAGS.items()}
    return PriorOverrides(
        **values,
        no_priors=bool(getattr(args, "prior_none", False)),
        from_truth=bool(getattr(args, "prior_from_truth", False)),
        perturb_seed=getattr(args, "prior_perturb_seed", None),
    )
