"""What a batch does to each session: the session folders under the given paths, and each
session's chain as a list of stages, each with the files it reads and writes.

A stage is a Python callable (the default chain's: `mocap run`'s stage functions) or a
`mocap` sub-command (its argument list, run as a child process); a stage with a
`camera` runs as its own task beside the session's other camera stages (tracking), every
other stage in the session's own task, in order.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from mocap.errors import InputError
from mocap.io.session import Session
from mocap.orchestration.pipeline import RunOptions, session_steps

_OUTPUT_FLAGS = ("--out", "--points")  # the flags whose value a stage writes
ANALYSIS_DIR = Path("results")  # where `mocap run`'s analyze stage writes cycles.csv


@dataclass(frozen=True)
class Stage:
    """One step of a session's chain.

    `args`: the `mocap` arguments (run as ``python -m mocap ARGS``), or `call`: a
    picklable callable of no argument, run in the worker (a report it returns goes to the
    stage's log); `inputs` and `outputs`: the files
    (or folders) it reads and writes, whose content hashes decide whether it must run again;
    `camera`: the camera of a per-camera stage (run as its own task), None otherwise.
    """

    name: str
    inputs: tuple[Path, ...]
    outputs: tuple[Path, ...]
    args: tuple[str, ...] = ()
    call: Callable[[], str | None] | None = field(default=None, compare=False)
    camera: str | None = None

    def __post_init__(self) -> None:
        if bool(self.args) == (self.call is not None):
            raise ValueError(f"stage {self.name!r}: give either mocap arguments or a callable")
        if not self.outputs:
            raise ValueError(f"stage {self.name!r}: a stage must write something")
        object.__setattr__(self, "args", tuple(str(a) for a in self.args))
        object.__setattr__(self, "inputs", tuple(Path(p) for p in self.inputs))
        object.__setattr__(self, "outputs", tuple(Path(p) for p in self.outputs))


def find_sessions(paths) -> list[Path]:
    """Every session folder (a folder holding session.toml) at or under `paths`, sorted, once."""
    found = set()
    for path in map(Path, paths):
        if not path.exists():
            raise InputError("not found; give session folders or folders that hold them", path=path)
        if path.is_file():
            raise InputError("is a file; give session folders or folders that hold them", path=path)
        if (path / "session.toml").is_file():
            found.add(path.resolve())
        found.update(p.parent.resolve() for p in path.rglob("session.toml") if p.is_file())
    return sorted(found)


def stage_from_command(name: str, args: list[str], made: set[Path]) -> Stage:
    """A stage from `mocap` arguments: it writes the values of --out / --points; it reads
    every absolute path argument that is an existing file or a file an earlier stage makes (`made`, updated)."""
    outputs = [Path(args[k + 1]) for k, a in enumerate(args[:-1]) if a in _OUTPUT_FLAGS]
    written = {k + 1 for k, a in enumerate(args[:-1]) if a in _OUTPUT_FLAGS}
    candidates = [Path(a) for k, a in enumerate(args) if k not in written and Path(a).is_absolute()]
    inputs = [p for p in candidates if p in made or p.is_file()]
    inputs = list(dict.fromkeys(inputs))  # once each, in order
    made.update(outputs)
    camera = args[args.index("--camera") + 1] if args[0] == "track" and "--camera" in args else None
    return Stage(name, tuple(inputs), tuple(outputs), args=tuple(args), camera=camera)


def default_chain(root: Path, options: RunOptions = RunOptions(view=False), analyze: bool = True) -> list[Stage]:
    """`mocap run`'s stages on the session (refine and view as in `options`), each calling
    its stage function; its analyze stage (a digging machine's: ``results/cycles.csv`` …)
    only with `analyze`."""
    made: set[Path] = set()
    stages = []
    for step in session_steps(Session.open(root), options):
        if step.name == "analyze" and not analyze:
            continue
        inputs = tuple(dict.fromkeys(p for p in step.inputs if p in made or p.is_file()))  # once each, in order
        made.update(step.outputs)
        stages.append(Stage(step.name, inputs, step.outputs, call=step.call, camera=step.camera))
    return stages


def split_tasks(stages: list[Stage]) -> list[list[Stage]]:
    """The chain cut into task groups: each run of session stages is one group (run in order,
    in one task); each camera stage is a group of its own, run beside the other camera stages
    of its run."""
    groups: list[list[Stage]] = []
    for stage in stages:
        if stage.camera is None and groups and groups[-1][-1].camera is None:
            groups[-1].append(stage)
        else:
            groups.append([stage])
    return groups
