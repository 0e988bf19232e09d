"""``imunoise fleet-report``: the fleet view of a catalogue as HTML (and JSON).

Per sensor model and channel, every unit's coefficients (its recordings pooled, with the 95 %
interval) and the units that are outliers against the population; per unit, the coefficients
over time and whether its recordings agree; with ``--limits``, pass or fail against given
limits. The limits file is YAML::

    "*":                        # any sensor model (or a model name as in the catalogue)
      gyro:                     # gyro, accel, or a channel name such as gyro_z
        N: {max: 0.3, unit: "deg/sqrt(h)"}
        B: {max: 10, unit: "deg/h"}
      accel:
        N: {max: 0.002}         # SI (m/s^2/sqrt(Hz)) when no unit is given
"""

from __future__ import annotations

import argparse
import sys

from imunoise.errors import UsageError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fleet-report", help="fleet view of a catalogue: populations, "
                       "outliers, units over time, limits", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("catalog", metavar="DIR", help="catalogue folder written by imunoise fleet")
    p.add_argument("-o", "--output", metavar="OUT.html", help="write the HTML page here")
    p.add_argument("--limits", metavar="LIMITS.yaml", help="coefficient limits (see above)")
    p.add_argument("--json", action="store_true", help="print the fleet document on stdout")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from imunoise.extras import require

    require("fleet", "imunoise fleet-report", ("pyarrow",))
    from imunoise.fleet.catalog import CatalogError, part_paths
    from imunoise.fleet.view import LimitsError, fleet_summary, load_limits

    if not Path(args.catalog).is_dir() or not part_paths(args.catalog):
        raise UsageError(f"fleet-report: {args.catalog}: no catalogue there (run imunoise "
                         "fleet FILES --catalog DIR first)")
    if not args.output and not args.json:
        raise UsageError("fleet-report: give -o OUT.html and/or --json")
    try:
        limits = load_limits(args.limits) if args.limits else None
        doc = fleet_summary(args.catalog, limits)
    except (LimitsError, CatalogError) as exc:
        raise UsageError(f"fleet-report: {exc}") from None
    if args.output:
        from imunoise.export.files import check_output_folder, write_text_atomically
        from imunoise.fleet.html import render_fleet

        check_output_folder(args.output)
        write_text_atomically(args.output, render_fleet(doc))
        print(f"wrote {args.output}: {doc['files']} recording(s), {len(doc['outliers'])} "
              f"outlier(s), {len(doc['grew'])} grown", file=sys.stderr)
    if args.json:
        from imunoise.pipeline import documents

        sys.stdout.write(documents.dumps(doc) + "\n")
    return 0
