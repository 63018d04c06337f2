"""Running a task's stages on a worker: skip what is up to date, run the rest, record them.

A task runs one group of a session's chain (`plan.split_tasks`) and hands its successor the
chain's file hashes so far (`TaskResult.state`). Session tasks write the manifest; camera
tasks, which run side by side, hand their records to the next session task instead. A
failing stage ends its session's chain with its error; it never raises into the scheduler.
"""

from __future__ import annotations

import functools
import logging
import os
import subprocess
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import mocap
from mocap.batch.manifest import Manifest
from mocap.batch.plan import Stage
from mocap.errors import EXIT_OK, EXIT_PARTIAL, InputError, Report, one_line
from mocap.progress import quiet_libraries

log = logging.getLogger(__name__)

LOG_DIR = Path("batch") / "logs"
RAN, SKIPPED, FAILED = "ran", "skipped", "failed"
PARTIAL = "partial"  # a session whose stages all ran, one or more doing part of its work


@dataclass(frozen=True)
class Outcome:
    stage: str
    status: str  # ran, skipped or failed
    seconds: float
    error: str = ""
    partial: str = ""  # a stage that did part of its work: its line (a camera not synchronised, ...)


@dataclass(frozen=True)
class TaskResult:
    """What a task hands on: state {file: hash} of the chain so far, its stages' outcomes, the
    manifest records it made but did not write (camera tasks), the first error if any."""

    state: dict
    outcomes: tuple[Outcome, ...] = ()
    records: dict = field(default_factory=dict)
    files: dict = field(default_factory=dict)
    error: str = ""


def _overwritten(chain: list[Stage], manifest: Manifest) -> set[tuple[str, str]]:
    """(stage, file) pairs whose file a later stage of the chain writes again."""
    later: set[str] = set()
    pairs = set()
    for stage in reversed(chain):
        keys = {manifest.key(p) for p in stage.outputs}
        pairs.update((stage.name, k) for k in keys & later)
        later |= keys
    return pairs


def _args(stage: Stage) -> tuple[str, ...]:
    """The stage's arguments, or for a callable its qualified name (and a partial's arguments)."""
    if stage.args:
        return stage.args
    call, bound = stage.call, ()
    if isinstance(call, functools.partial):
        call, bound = call.func, tuple(map(str, call.args)) + tuple(f"{k}={v}" for k, v in call.keywords.items())
    return (f"call:{getattr(call, '__module__', '')}.{getattr(call, '__qualname__', type(call).__name__)}", *bound)


def _input_hashes(stage: Stage, manifest: Manifest, state: dict) -> dict[str, str]:
    hashes = {}
    for path in stage.inputs:
        key = manifest.key(path)
        hashes[key] = state[key] if key in state else (manifest.hash(path) or "missing")
    return hashes


def up_to_date(stage: Stage, manifest: Manifest, inputs: dict, overwritten) -> bool:
    record = manifest.stages.get(stage.name)
    if record is None or record.get("args") != manifest.args_key(_args(stage)) or record.get("inputs") != inputs:
        return False
    for path in stage.outputs:
        key = manifest.key(path)
        if key not in record.get("outputs", {}):
            return False
        if (stage.name, key) not in overwritten and manifest.hash(path) != record["outputs"][key]:
            return False
    return True


def execute(stage: Stage, root: Path) -> str:
    """Run one stage; its report goes to batch/logs/<stage>.log. Returns '' or the error, as
    a `Report` whose `partial` is the stage's line when it did part of its work (exit status 3).

    A callable stage runs inside the worker's process (its modules stay imported from one
    stage to the next); a stage of `mocap` arguments runs as that command in a child process.
    """
    log_path = root / LOG_DIR / f"{stage.name.replace(' ', '_')}.log"
    if stage.call is None:
        log_path.parent.mkdir(parents=True, exist_ok=True)
        code, errors = _child_process(stage.args, log_path)
        lines = [line for line in errors.splitlines() if line.strip()]
        if code in (EXIT_OK, EXIT_PARTIAL):
            return Report("", lines[-1] if code == EXIT_PARTIAL and lines else "")
        return lines[-1] if lines else f"exit status {code}"
    quiet_libraries()
    report = ""
    try:
        report = stage.call()
    except InputError as exc:  # the one line a command would print
        error = one_line(str(exc))
    except Exception as exc:  # a failed stage is reported, the batch goes on; its traceback in the log
        error = f"{type(exc).__name__}: {exc}"
        report = traceback.format_exc()
    else:
        error = ""
    if isinstance(report, str) and (report or error):
        log_path.parent.mkdir(parents=True, exist_ok=True)
        with open(log_path, "w", encoding="utf-8") as out:
            out.write("".join(f"{text}\n" for text in (report, error) if text))
    return Report(error, "" if error else getattr(report, "partial", ""))


def _child_process(args, log_path: Path) -> tuple[int, str]:
    env = dict(os.environ)
    package_root = str(Path(mocap.__file__).resolve().parents[1])  # this worker's mocap, for the stage too
    env["PYTHONPATH"] = os.pathsep.join(p for p in (package_root, env.get("PYTHONPATH", "")) if p)
    with open(log_path, "w", encoding="utf-8") as out:
        done = subprocess.run([sys.executable, "-m", "mocap", *args], stdout=out, stderr=subprocess.PIPE,
                              text=True, env=env, stdin=subprocess.DEVNULL)
        out.write(done.stderr)
    return done.returncode, done.stderr


def run_stages(root: Path, chain: list[Stage], names: list[str], priors: list[TaskResult], write: bool) -> TaskResult:
    """Run the stages `names` of `chain` on the session `root` after the tasks `priors`.

    `write`: save the manifest (session tasks); camera tasks return their records instead.
    """
    root = Path(root)
    manifest = Manifest.load(root)
    state: dict = {}
    for prior in priors:
        state.update(prior.state)
        manifest.stages.update(prior.records)
        manifest.files.update(prior.files)
    if write and any(prior.records for prior in priors):
        manifest.save()
    failed = [prior.error for prior in priors if prior.error]
    if failed:
        return TaskResult(state, error=failed[0])
    overwritten = _overwritten(chain, manifest)
    stages = {stage.name: stage for stage in chain}
    outcomes, records = [], {}
    for name in names:
        stage = stages[name]
        inputs = _input_hashes(stage, manifest, state)
        if up_to_date(stage, manifest, inputs, overwritten):
            state.update(manifest.stages[name]["outputs"])
            outcomes.append(Outcome(name, SKIPPED, 0.0, partial=manifest.stages[name].get("partial", "")))
            continue
        for path in stage.inputs:  # an input a later stage rewrote: put back what this stage read
            key = manifest.key(path)
            if key in state and manifest.hash(path) != state[key] and not manifest.restore(path, state[key]):
                error = f"{key} changed after its stage ran; delete {root / 'batch'} to run the session afresh"
                outcomes.append(Outcome(name, FAILED, 0.0, error))
                return TaskResult(state, tuple(outcomes), records, manifest.files, f"{name}: {error}")
        start = time.perf_counter()
        error = execute(stage, root)
        partial, error = getattr(error, "partial", ""), str(error)
        seconds = time.perf_counter() - start
        missing = [str(p) for p in stage.outputs if not p.exists()]
        if not error and missing:
            error = f"wrote no {', '.join(missing)}"
        if error:
            log.info("%s: %s failed: %s", root.name, name, error)
            outcomes.append(Outcome(name, FAILED, seconds, error))
            return TaskResult(state, tuple(outcomes), records, manifest.files, f"{name}: {error}")
        outputs = {manifest.key(p): manifest.hash(p) for p in stage.outputs}
        for path in stage.outputs:
            if (name, manifest.key(path)) in overwritten:
                manifest.keep(path, outputs[manifest.key(path)])
        manifest.record(name, _args(stage), inputs, outputs, seconds)
        if partial:  # kept, so that a re-run that skips the stage still reports it
            manifest.stages[name]["partial"] = partial
        records[name] = manifest.stages[name]
        state.update(outputs)
        outcomes.append(Outcome(name, RAN, seconds, partial=partial))
        if write:
            manifest.save()
    return TaskResult(state, tuple(outcomes), {} if write else records, manifest.files)
