"""`mocap batch`: every session under the given paths through its chain on Dask distributed,
then the fleet summary. Load (find the sessions, plan their chains) -> compute (the task
graph on the cluster) -> save (fleet.csv, fleet_report.md) -> a short report.

Per session the graph is: the session stages before tracking (calibrate) -> one task per
camera (track) -> the session stages after (sync … fit, analyze) -> a summary task. Only
the client plans; only workers touch the session folders after that.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from mocap.batch.fleet import SessionSummary, cycle_figures, machine_and_day, report_text
from mocap.batch.plan import ANALYSIS_DIR, Stage, default_chain, find_sessions, split_tasks
from mocap.batch.run import FAILED, PARTIAL, RAN, SKIPPED, TaskResult, run_stages
from mocap.errors import InputError
from mocap.progress import progress

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BatchOptions:
    """`scheduler`: address of a running Dask scheduler (None: a local cluster of `workers`
    single-threaded workers); `out`: folder of fleet.csv and fleet_report.md; `refine`,
    `view`: as `mocap run --refine` / without `--no-view`."""

    scheduler: str | None = None
    workers: int = 2
    out: Path = Path(".")
    refine: bool = False
    view: bool = False
    tls_ca_file: Path | None = None  # a tls:// scheduler's: the cluster's CA, this client's certificate and key (PEM)
    tls_cert: Path | None = None
    tls_key: Path | None = None

    def __post_init__(self) -> None:
        if self.workers < 1:
            raise ValueError(f"workers must be at least 1, got {self.workers}")
        given = [flag for flag, value in (("--tls-ca-file", self.tls_ca_file), ("--tls-cert", self.tls_cert),
                                          ("--tls-key", self.tls_key)) if value is not None]
        if given and not (self.scheduler or "").startswith("tls://"):
            raise ValueError(f"{given[0]} is for a cluster reached over TLS: give --scheduler tls://HOST:PORT")
        if given and (self.tls_ca_file is None or self.tls_cert is None):
            raise ValueError("TLS needs the cluster's CA (--tls-ca-file) and this client's certificate (--tls-cert, "
                             "with --tls-key unless the certificate file holds the key)")


_TLS_CONFIG = "distributed.comm.tls"  # Dask's own settings of the files, used when no flag gives them


def cluster_security(options: BatchOptions):
    """Dask's `Security` for a tls:// scheduler (None for any other): the files of
    `options`, or else Dask's own configuration (``distributed.comm.tls.ca-file``,
    ``.client.cert``, ``.client.key``). A file missing or unreadable, or not a PEM
    certificate or key, is an InputError naming it."""
    import ssl

    import dask
    from distributed.security import Security

    if not (options.scheduler or "").startswith("tls://"):
        return None
    if options.tls_ca_file is not None:
        files = {"--tls-ca-file": options.tls_ca_file, "--tls-cert": options.tls_cert, "--tls-key": options.tls_key}
    else:
        files = {f"{_TLS_CONFIG}.{k}": dask.config.get(f"{_TLS_CONFIG}.{k}", None)
                 for k in ("ca-file", "client.cert", "client.key")}
        if not all(list(files.values())[:2]):
            raise InputError("a tls:// scheduler needs the cluster's CA and this client's certificate: give "
                             "--tls-ca-file, --tls-cert and --tls-key (PEM files), or set them in Dask's "
                             f"configuration ({_TLS_CONFIG}.ca-file, .client.cert, .client.key)", where=options.scheduler)
    for flag, path in files.items():
        if path is None:
            continue
        try:
            with open(path, "rb"):
                pass
        except OSError as exc:
            raise InputError(f"{flag}: cannot read it ({exc.strerror or exc}); give the PEM file", path=path) from None
    ca, cert, key = (None if v is None else str(v) for v in files.values())
    try:
        ssl.create_default_context(cafile=ca)
    except ssl.SSLError as exc:
        raise InputError(f"not a PEM certificate of a CA ({exc.reason or exc}); give the cluster's CA file",
                         path=ca) from None
    try:
        ssl.create_default_context().load_cert_chain(cert, key)
    except ssl.SSLError as exc:
        raise InputError(f"the certificate and its key do not load ({exc.reason or exc}); give this client's PEM "
                         "certificate and its key", path=cert if key is None else f"{cert}, {key}") from None
    return Security(tls_ca_file=ca, tls_client_cert=cert, tls_client_key=key, require_encryption=True)


CONNECT_TIMEOUT_S = 5.0  # how long a scheduler given by --scheduler may take to answer


@contextlib.contextmanager
def dask_client(scheduler: str | None, workers: int, security=None):
    """A Dask client: of the scheduler at `scheduler` (over TLS with `security`, Dask's
    `Security`), or of an embedded local cluster."""
    from distributed import Client, LocalCluster

    if not log.isEnabledFor(logging.DEBUG):  # Dask's own start-up and shut-down lines only with -v -v
        logging.getLogger("distributed").setLevel(logging.WARNING)
    if scheduler:
        try:
            client = Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s", security=security)
        except (OSError, TimeoutError) as exc:
            raise InputError(
                f"cannot reach the Dask scheduler ({exc}); start one with `dask scheduler` and workers "
                "with `dask worker ADDRESS`, or leave out --scheduler for a local cluster",
                where=scheduler,
            ) from None
        with client:
            yield client
        return
    import dask

    # the workers' statistical profiler samples every thread 100 times a second: 15 % more CPU here
    # a worker killed mid-task also fails the tasks queued on it: more than Dask's 3 deaths allowed per task
    with dask.config.set({"distributed.worker.profile.enabled": False, "distributed.scheduler.allowed-failures": 10}):
        with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
            with Client(cluster) as client:
                yield client


def summarize(root: Path, label: str, results: list[TaskResult]) -> SessionSummary:
    """A session's summary (named `label`) from its tasks' results and, if its chain ran, its cycles."""
    from mocap.io.cycles_csv import load_cycles
    from mocap.io.motion_csv import load_motion
    from mocap.io.session import Session

    session = Session.open(root)
    config = session.config()
    machine, day = machine_and_day(config.metadata, config.machine)
    outcomes = [o for r in results for o in r.outcomes]
    counts = {
        "stages_run": sum(o.status == RAN for o in outcomes),
        "stages_skipped": sum(o.status == SKIPPED for o in outcomes),
        "stage_seconds": sum(o.seconds for o in outcomes),
    }
    error = next((r.error for r in results if r.error), "")
    if error:
        return SessionSummary(label, machine, day, FAILED, error, **counts)
    cycles_path = root / ANALYSIS_DIR / "cycles.csv"
    try:
        n_frames = len(load_motion(session.motion_path, session.machine())) if session.motion_path.is_file() else 0
        cycles = load_cycles(cycles_path) if cycles_path.is_file() else None
    except InputError as exc:
        return SessionSummary(label, machine, day, FAILED, f"summary: {exc}", **counts)
    figures = cycle_figures(cycles, config.cameras[0].fps, n_frames)
    partial = "; ".join(f"{o.stage}: {o.partial}" for o in outcomes if o.partial)
    return SessionSummary(label, machine, day, PARTIAL if partial else "ok", partial, **counts, **figures)


def _failed(root: Path, label: str, error: str) -> SessionSummary:
    from mocap.io.session_toml import load_session_config

    try:
        config = load_session_config(root / "session.toml")
        machine, day = machine_and_day(config.metadata, config.machine)
    except InputError:
        machine, day = "unknown", "unknown"
    return SessionSummary(label, machine, day, FAILED, error)


def submit_session(client, root: Path, label: str, chain: list[Stage]):
    """Submit a session's tasks; returns the future of its summary."""
    previous, cameras, tasks = [], [], []
    for group in split_tasks(chain):
        names = [stage.name for stage in group]
        key = f"{root.name}:{names[0].replace(' ', '_')}-{time.time_ns()}"
        if group[0].camera is not None:
            future = client.submit(run_stages, root, chain, names, previous, False, key=key)
            cameras.append(future)
        else:
            future = client.submit(run_stages, root, chain, names, cameras or previous, True, key=key)
            previous, cameras = [future], []
        tasks.append(future)
    return client.submit(summarize, root, label, tasks, key=f"{root.name}:summary-{time.time_ns()}")


def session_labels(sessions: list[Path]) -> dict[Path, str]:
    """Each session's name in the summary: its path below the sessions' common folder."""
    if len(sessions) == 1:
        return {sessions[0]: sessions[0].name}
    common = Path(os.path.commonpath(sessions))
    return {root: root.relative_to(common).as_posix() for root in sessions}


def analyze_available() -> bool:
    from importlib.util import find_spec

    return find_spec("mocap.analysis.stage") is not None


def run_batch(paths, options: BatchOptions, chain_for: Callable[[Path], list[Stage]] | None = None) -> tuple[str, int]:
    """Run every session under `paths`; write fleet.csv and fleet_report.md into
    `options.out`. Returns the short report and the number of sessions failed or partial
    (every stage ran, one did part of its work: a camera not synchronised, frames unexplained).

    `chain_for(root)` gives a session's stages; by default `mocap run`'s (as `options`
    say) and then `mocap analyze`.
    """
    from mocap.io.atomic import write_text
    from mocap.io.fleet_csv import save_fleet
    from mocap.io.lock import folder_lock
    from mocap.orchestration.pipeline import RunOptions

    start = time.perf_counter()
    sessions = find_sessions(paths)
    if not sessions:
        raise InputError("no session folder (with session.toml) under the given paths", where=", ".join(map(str, paths)))
    if chain_for is None:
        analyze = analyze_available()
        if not analyze:
            log.warning("`mocap analyze` is not available: the sessions get no cycle analysis")
        run_options = RunOptions(refine=options.refine, view=options.view)

        def chain_for(root: Path) -> list[Stage]:
            return default_chain(root, run_options, analyze=analyze)

    labels = session_labels(sessions)
    summaries: dict[Path, SessionSummary] = {}
    security = cluster_security(options)
    with contextlib.ExitStack() as held:
        for root in sessions:  # each session's lock held while its tasks run (a killed batch's is taken over)
            try:
                held.enter_context(folder_lock(root, "mocap batch"))
            except InputError as exc:  # another command writes it: listed as failed, the others go on
                summaries[root] = _failed(root, labels[root], str(exc))
        with dask_client(options.scheduler, options.workers, security) as client:
            futures = {}
            for root in sessions:
                if root in summaries:
                    continue
                try:
                    futures[root] = submit_session(client, root, labels[root], chain_for(root))
                except InputError as exc:
                    summaries[root] = _failed(root, labels[root], str(exc))
            from distributed import as_completed

            order = {future.key: root for root, future in futures.items()}
            for future in progress(as_completed(futures.values()), total=len(futures), desc="sessions",
                                   unit="session"):
                root = order[future.key]
                try:
                    summaries[root] = future.result()
                except Exception as exc:  # a worker died under the session (out of memory, a crash)
                    summaries[root] = _failed(root, labels[root], f"{type(exc).__name__}: {exc}")
    ordered = [summaries[root] for root in sessions]
    wall = time.perf_counter() - start
    save_fleet(ordered, Path(options.out) / "fleet.csv")
    write_text(Path(options.out) / "fleet_report.md", report_text(ordered, wall))
    failed = [s for s in ordered if s.status == FAILED]
    partial = [s for s in ordered if s.status == PARTIAL]
    lines = [f"{len(ordered)} sessions in {wall:.1f} s: {len(ordered) - len(failed) - len(partial)} ok, "
             + (f"{len(partial)} partial, " if partial else "")
             + f"{len(failed)} failed; {sum(s.stages_run for s in ordered)} stages run, "
             f"{sum(s.stages_skipped for s in ordered)} up to date"]
    lines += [f"  {s.session}: {s.error}" for s in failed]
    lines += [f"  {s.session}: partial: {s.error}" for s in partial]
    lines.append(f"wrote {Path(options.out) / 'fleet.csv'} and {Path(options.out) / 'fleet_report.md'}")
    return "\n".join(lines), len(failed) + len(partial)
