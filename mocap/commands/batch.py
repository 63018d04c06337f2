"""`mocap batch`: every session folder under the paths through the whole chain, on Dask."""

from __future__ import annotations

import argparse
from pathlib import Path

from mocap.commands import COMMANDS

EXAMPLE = """examples:
  mocap batch sessions/ --workers 2 --out fleet/          # an embedded local cluster of 2 workers
  dask scheduler &  dask worker tcp://HOST:8786 &          # or a cluster of your own
  mocap batch sessions/ --scheduler tcp://HOST:8786 --out fleet/
  mocap batch sessions/ --scheduler tls://HOST:8786 --tls-ca-file ca.pem --tls-cert me.pem --tls-key me.key"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "batch",
        help=COMMANDS["batch"],
        description="Run every session folder (a folder with session.toml) under the paths through "
        "`mocap run`'s stages and the cycle analysis on Dask distributed: tracking one task per camera, the "
        "rest one task per session. A stage whose inputs have not changed since it last ran (content hashes "
        "in SESSION/batch/manifest.toml) is skipped; a failing session is reported and the others go on. "
        "Writes fleet.csv and fleet_report.md (cycles per hour, cycle times, class mix per session, "
        "machine and day). Exit status 3 (partial) if a session failed: the others are done.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("paths", nargs="+", type=Path, help="session folders or folders holding them")
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                   help="a running Dask scheduler, tcp:// or tls:// (default: a local cluster)")
    p.add_argument("--tls-ca-file", type=Path, metavar="CA.pem",
                   help="with a tls:// scheduler: the cluster's CA certificate (default: Dask's configuration, "
                   "distributed.comm.tls.ca-file)")
    p.add_argument("--tls-cert", type=Path, metavar="CERT.pem", help="with a tls:// scheduler: this client's certificate")
    p.add_argument("--tls-key", type=Path, metavar="KEY.pem",
                   help="with a tls:// scheduler: this client's private key (unless the certificate file holds it)")
    p.add_argument("--workers", type=int, default=2, help="workers of the local cluster (default 2)")
    p.add_argument("--out", type=Path, default=Path("."), help="folder for fleet.csv and fleet_report.md (default .)")
    p.add_argument("--refine", action="store_true", help="bundle-adjust each session's cameras, as `mocap run --refine`")
    p.add_argument("--view", action="store_true", help="also record each session's Rerun replay")
    p.set_defaults(run=run)


def run(args) -> int:
    from mocap.batch.stage import BatchOptions, run_batch
    from mocap.errors import EXIT_OK, EXIT_PARTIAL, InputError

    try:
        options = BatchOptions(args.scheduler, args.workers, args.out, args.refine, args.view,
                               args.tls_ca_file, args.tls_cert, args.tls_key)
    except ValueError as exc:
        raise InputError(f"bad option: {exc}") from None
    report, failed = run_batch(args.paths, options)
    print(report)
    return EXIT_PARTIAL if failed else EXIT_OK
