"""`aeroloc …` sub-commands. Thin: each command lives in ``aeroloc.commands.<name>`` with
``add_arguments(parser)`` and ``run(args) -> int``; this file only dispatches and turns
:class:`AerolocError` (and other expected failures) into a one-line message and a non-zero exit."""

from __future__ import annotations

import argparse
import importlib
import sys

from aeroloc.core.errors import AerolocError

# command name -> (module under aeroloc.commands, one-line help)
COMMANDS = {
    "tiles": ("tiles", "cut a map into a tile database at a zoom and overlap"),
    "build": ("build", "build a retrieval database: tiles + descriptors + index (+ local features)"),
    "retrieve": ("retrieve", "top-N tiles per query by global descriptor"),
    "localize": ("localize", "retrieve, re-rank and align: latitude/longitude per query"),
    "track": (
        "track",
        "localize a whole flight (frames, photos or video): a filtered track, GeoJSON/KML/HTML, MAVLink",
    ),
    "simulate-flight": ("simulate_flight", "fly a path over a real image and write frames + telemetry + truth"),
    "evaluate": ("evaluate", "score a results CSV: VPR Recall@N, Georeference Recall@d"),
    "bench": ("bench", "run an experiment file (sweeps, tables, plots, report)"),
    "download": ("download", "download a map from a tile server or the Google Static Maps API"),
    "import": ("import_map", "import a GeoTIFF/COG orthophoto as a map folder"),
    "demo": ("demo", "the end-to-end demo on ../shared/data"),
    "methods": ("methods", "list the retrieval methods and re-rankers"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="aeroloc", description="GNSS-free localization of aerial images against georeferenced maps."
    )
    parser.add_argument("--version", action="version", version=f"aeroloc {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_) in COMMANDS.items():
        try:
            mod = importlib.import_module(f"aeroloc.commands.{module}")
        except ModuleNotFoundError as exc:
            if exc.name == f"aeroloc.commands.{module}":
                continue  # command not shipped in this build
            raise
        p = sub.add_parser(name, help=help_, description=(mod.__doc__ or help_).strip().splitlines()[0])
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def _version() -> str:
    from aeroloc import __version__

    return __version__


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except AerolocError as exc:
        print(f"aeroloc {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(
            f"aeroloc {args.command}: interrupted; finished work is kept, run the same command to resume",
            file=sys.stderr,
        )
        return 130


if __name__ == "__main__":
    sys.exit(main())
