"""Killing a command at chosen moments, and what a reader then sees: shared by the
kill-and-resume tests (tests/test_faults.py) and the kill soak (benchmarks/bench_faults.py)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def visible(root) -> dict[str, str]:
    """{relative path: sha256} of the files under `root` a reader takes for results (hidden
    temporaries and lock files excluded)."""
    from badinput_files import snapshot

    return {k: v for k, v in snapshot(root).items() if not any(part.startswith(".") for part in k.split("/"))}


class Forked:
    """`mocap argv` in a fork of this process, in a process group of its own, its output
    discarded: the command as `python -m mocap.cli` runs it (`cli.main`), without the start
    of a new interpreter (its imports, the compiled kernels loaded from numba's cache) when
    this process has run the command before. Only for commands that start no thread pool of
    this process's (not `batch`: its Dask client). Polled and waited for as a `Popen`."""

    def __init__(self, argv: list[str], cwd) -> None:
        from tqdm import tqdm

        tqdm.monitor_interval = 0  # no thread of this process may hold tqdm's lock at the fork
        if tqdm.monitor is not None:
            tqdm.monitor.exit()
            tqdm.monitor = None
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:  # the child: never returns into the test
            code = 1
            try:
                os.setpgid(0, 0)
                os.chdir(cwd)
                null = os.open(os.devnull, os.O_RDWR)
                for fd in (0, 1, 2):
                    os.dup2(null, fd)
                sys.stdout = sys.stderr = open(os.devnull, "w")
                from mocap import cli

                code = cli.main(list(map(str, argv)))
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else 1
            except BaseException:
                code = 1
            finally:
                os._exit(code or 0)
        try:
            os.setpgid(pid, pid)  # (the child does it too: whichever comes first)
        except OSError:
            pass  # it has done it, or ended
        self.pid = pid
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            done, status = os.waitpid(self.pid, os.WNOHANG)
            if done:
                self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            if deadline is not None and time.monotonic() >= deadline:
                raise subprocess.TimeoutExpired(f"mocap (pid {self.pid})", timeout)
            time.sleep(0.002)
        return self.returncode


AFTER_AT_MOST = 300.0  # s a killed child may take to reach the moment its kill counts from


def run_killed(argv: list[str], cwd, delay: float, after=None, fork: bool = False) -> int | None:
    """Run `mocap argv` in a child process and SIGKILL it, and every process it started (a
    batch's Dask workers), after `delay` s, counted from when `after()` first holds if given
    (None: it ended first, its exit status else). `fork`: the child a fork of this process
    (`Forked`), else a new interpreter."""
    if fork:
        child = Forked(argv, cwd)
    else:
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        child = subprocess.Popen([sys.executable, "-m", "mocap.cli", *argv], cwd=cwd, env=env,
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    waited = time.monotonic() + AFTER_AT_MOST
    while after is not None and child.poll() is None and not after():
        if time.monotonic() > waited:  # a child stuck before its moment: a failure, never a hung suite
            os.killpg(child.pid, signal.SIGKILL)
            child.wait()
            raise AssertionError(f"mocap {' '.join(map(str, argv))}: still running, its moment not reached "
                                 f"after {AFTER_AT_MOST:g} s")
        time.sleep(0.002)
    try:
        return child.wait(timeout=delay)
    except subprocess.TimeoutExpired:
        os.killpg(child.pid, signal.SIGKILL)
        child.wait()
        deadline = time.monotonic() + 10
        while group_alive(child.pid) and time.monotonic() < deadline:  # its workers gone too
            time.sleep(0.05)
        return None


def group_alive(group: int) -> bool:
    try:
        os.killpg(group, 0)
    except ProcessLookupError:
        return False
    return True


def kill_at(argv: list[str], cwd, delays, check, after=None, fork: bool = False) -> list[int | None]:
    """Run `mocap argv` killed after each of `delays` s in turn (from when `after()` holds if
    given), each run taking up what the last one left; `check()` after each. A run that ends
    before its moment (a machine faster than timed) must end with 0, and is run again with half
    the delay. Returns the exit statuses (None: killed); every moment killed one."""
    codes = []
    for delay in delays:
        for _ in range(3):
            codes.append(run_killed(argv, cwd, delay, after, fork))
            assert codes[-1] in (None, 0), codes
            check()
            if codes[-1] is None:
                break
            delay /= 2
        assert codes[-1] is None, codes  # killed mid-way
    return codes


def make_small_session(root: Path) -> Path:
    """A session as a user brings it to `mocap run`: two cameras at 480x270 and 5 fps, one dig
    cycle, the calibration frame's labels digitised."""
    from mocap import cli
    from mocap.io.session import Session
    from mocap.orchestration.demo import digitise_first_frame

    assert cli.main(["synth", "--machine", "hitachi_ex3500", "--cameras", "2", "--cycles", "1", "--size", "480x270",
                     "--fps", "5", "--clean", "--out", str(root)]) == 0
    digitise_first_frame(Session.open(root), np.random.default_rng(1))
    return root


def timed_warm(run) -> tuple[float, bool]:
    """Run `run()` (a command in this process): its seconds, and whether it compiled a kernel
    of the project on the way (numba's on-disk cache empty, as on a fresh checkout). The
    kills' moments are shares of a run that compiles nothing: a run that compiled is a warm-up
    only, and the caller times another."""
    import time

    from numba.core import event

    with event.install_recorder("numba:compile") as recorder:
        start = time.perf_counter()
        run()
        took = time.perf_counter() - start
    compiled = any(getattr(getattr(data.data["dispatcher"], "py_func", None), "__module__", "").startswith("mocap")
                   for _, data in recorder.buffer)
    return took, compiled
