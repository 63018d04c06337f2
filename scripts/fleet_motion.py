"""Many sessions' motion in one table: every processed session (a folder with session.toml
and results/motion.csv) under the folders given, one row per frame with a `session` column,
written as one Parquet (or CSV) file — for a notebook, pandas, DuckDB or a spreadsheet.

    python scripts/fleet_motion.py sessions/ --out fleet_motion.parquet

In a notebook:

    import mocap
    table = mocap.motions(["sessions/day1", "sessions/day2", "sessions/day3"])
    df = table.to_pandas()            # needs pandas; `table` is a pyarrow Table either way
    df.groupby("session").bucket_tip_z.max()
"""

import argparse
from pathlib import Path

import pyarrow.csv
import pyarrow.parquet

import mocap


def processed_sessions(folders: list[Path]) -> list[Path]:
    found = {p.parent for folder in folders for p in folder.rglob("session.toml")}
    return sorted(root for root in found if (root / "results" / "motion.csv").is_file())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", nargs="+", type=Path, help="session folders or folders holding them")
    parser.add_argument("--out", type=Path, default=Path("fleet_motion.parquet"), help=".parquet or .csv to write")
    args = parser.parse_args()
    sessions = processed_sessions(args.folders)
    if not sessions:
        print("no processed session (with results/motion.csv) under the folders given")
        return 1
    try:
        table = mocap.motions(sessions)
    except mocap.InputError as exc:
        print(f"error: {exc}")
        return 2
    if args.out.suffix == ".csv":
        pyarrow.csv.write_csv(table, args.out)
    else:
        pyarrow.parquet.write_table(table, args.out)
    print(f"{table.num_rows} frames of {len(sessions)} sessions written to {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
