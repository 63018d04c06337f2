import os

# The replay tests stream to a port where no viewer listens, on purpose; keep the Rerun
# SDK's own connection-retry log lines (printed when the process exits) out of the output.
os.environ.setdefault("RUST_LOG", "off")
# The suite runs on every core at once (pytest-xdist): a BLAS that also starts a thread per
# core in each worker oversubscribes them, and OpenBLAS's spinning threads then make a small
# SVD tens of times slower. One BLAS thread per worker (and per command the tests start).
for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")
# Bytecode is cached even where the environment asks otherwise (PYTHONDONTWRITEBYTECODE): on a
# fresh checkout every worker would compile the test modules (with pytest's assert rewriting)
# and the package's modules, and every command a test starts the package's modules, again.
if os.environ.pop("PYTHONDONTWRITEBYTECODE", None) is not None:
    import sys

    sys.dont_write_bytecode = False

import numpy as np
import pytest

from mocap.calibration import Observations
from mocap.io.machine_toml import load_machine
from mocap.synthetic.scenes import observe, random_joints, ring_of_cameras


@pytest.fixture(scope="session")
def ex3500():
    return load_machine("hitachi_ex3500")


@pytest.fixture(scope="session")
def bobcat():
    return load_machine("bobcat_225")


@pytest.fixture(scope="session")
def cube_pair():
    return load_machine("cube_pair")


def scene(machine, n_cameras, seed, noise_px=0.5, distance=(2.5, 4.0), outliers=0, joints=None):
    """Cameras around `machine` at `distance` times its extent, a random pose and the
    observations of one frame as calibration input."""
    rng = np.random.default_rng(seed)
    rest = machine.markers(np.zeros((1, machine.n_joints)))[0]
    extent = np.ptp(rest, axis=0).max()
    target = rest.mean(axis=0)
    cameras = ring_of_cameras(
        n_cameras, target, (distance[0] * extent, distance[1] * extent), rng,
        height=(0.3 * extent, 0.8 * extent),
    )
    q = random_joints(machine, 1, rng)[0] if joints is None else np.asarray(joints, dtype=float)
    tracks = observe(cameras, machine, q[None], rng, noise_px=noise_px, outliers=outliers)
    index = {c.name: i for i, c in enumerate(cameras)}
    obs = Observations(
        np.array([index[c] for c in tracks.camera]), machine.marker_index(tracks.marker), tracks.xy
    )
    return cameras, q, obs, tracks


def reasonable_guess(truth, rng):
    """A start for the paper's test of reasonable guesses: the true PaperCamera `truth` with its
    angles off by up to 30 deg, its position by 30 % and its focal length by a factor of 2."""
    from mocap.core.camera import PaperCamera

    return PaperCamera(
        truth.azimuth + np.radians(rng.uniform(-30, 30)),
        truth.elevation + np.radians(rng.uniform(-30, 30)),
        truth.tilt + np.radians(rng.uniform(-30, 30)),
        truth.position * rng.uniform(0.7, 1.3, 3),
        truth.focal * 2.0 ** rng.uniform(-1, 1),
    )


def write_opencv_intrinsics(path, size, matrix, distortion) -> None:
    """An OpenCV FileStorage (YAML or XML by the suffix) of one camera's intrinsics, as
    OpenCV's calibration samples write it: a file the project did not make."""
    import cv2

    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    storage.write("image_width", int(size[0]))
    storage.write("image_height", int(size[1]))
    storage.write("camera_matrix", np.asarray(matrix, dtype=float))
    storage.write("distortion_coefficients", np.asarray(distortion, dtype=float).reshape(1, -1))
    storage.release()


def _kernels_cached() -> bool:
    """Whether every module of the project with a cached kernel has a numba cache index at
    least as new as its source (numba's own test of a stale cache is the source's stamp)."""
    from pathlib import Path

    if os.environ.get("NUMBA_CACHE_DIR"):
        return False
    for source in (Path(__file__).parent.parent / "mocap").rglob("*.py"):
        if "cache=True" not in source.read_text():
            continue
        indexes = list((source.parent / "__pycache__").glob(f"{source.stem}.*.nbi"))
        if not indexes or max(p.stat().st_mtime for p in indexes) < source.stat().st_mtime:
            return False
    return True


def pytest_configure(config):
    """On a fresh checkout, before the whole suite (the README's command: no test named), the
    project's kernels are compiled into numba's cache by two processes at once
    (tests/warm_kernels.py), so that the workers and the commands the tests start load them
    rather than each compiling them all; a third collects the tests once, caching their
    bytecode for the workers."""
    import subprocess
    import sys
    from pathlib import Path

    if hasattr(config, "workerinput") or config.args_source != pytest.Config.ArgsSource.TESTPATHS:
        return
    if config.getoption("collectonly") or _kernels_cached():
        return
    script = Path(__file__).with_name("warm_kernels.py")
    warmers = [subprocess.Popen([sys.executable, str(script), part], stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL) for part in ("tracking", "reconstruct")]
    # and the test modules collected once, so that their bytecode (asserts rewritten) is cached
    # for the workers rather than compiled by each
    warmers.append(subprocess.Popen([sys.executable, "-m", "pytest", "--collect-only", "-q", "-n", "0",
                                     "-p", "no:cacheprovider", str(Path(__file__).parent)],
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
    for warmer in warmers:
        try:
            warmer.wait(timeout=600)
        except subprocess.TimeoutExpired:  # a warm-up that hangs only costs its time, never the suite
            warmer.kill()


def pytest_collection_modifyitems(items):
    """The tests marked `long` (tens of seconds each) first: with xdist's work stealing they
    start at once, and the short ones fill both cores around them, so that no long test is
    left to run alone at the end. Among them those marked `processes` (their Dask workers run
    the compiled kernels) come last: on a fresh checkout numba's cache is empty, and a test
    run first in this process (the demo's chain) compiles the kernels once and caches them,
    where each worker process would compile them all again."""
    items.sort(key=lambda item: (item.get_closest_marker("long") is None,
                                 item.get_closest_marker("processes") is not None))


def pytest_terminal_summary(terminalreporter):
    """The bad-input corpus (test_bad_input.py, cases named command/case) counted per command."""
    counts: dict[str, list[int]] = {}
    for outcome in ("passed", "failed"):
        for report in terminalreporter.stats.get(outcome, []):
            nodeid = getattr(report, "nodeid", "")
            if "test_bad_input.py::test_bad_input[" not in nodeid or getattr(report, "when", "call") != "call":
                continue
            command = nodeid.split("[", 1)[1].split("/", 1)[0]
            counts.setdefault(command, [0, 0])[outcome == "failed"] += 1
    if counts:
        terminalreporter.write_sep("-", "bad-input corpus per command (passed / cases)")
        for command, (passed, failed) in sorted(counts.items()):
            terminalreporter.write_line(f"{command:>12}: {passed} / {passed + failed}")
        total = sum(p for p, _ in counts.values()), sum(p + f for p, f in counts.values())
        terminalreporter.write_line(f"{'all':>12}: {total[0]} / {total[1]}")
