"""`mocap live`: sources -> the tracker of `mocap track`, frame by frame, one thread per
camera -> the warm-started fit and the fixed-lag smoother on the main thread -> rows to the
poses file and the feed.

The rows follow the clock camera: the reference camera (the calibration's first among the
sources), or while it has ended, the first camera still delivering; a row's frame is the
reference camera's frame at that time. A frame's own fit waits for every other running
camera's frame at or after its time (to interpolate between the two either side), at most
`wait_frames` reference intervals after its frame arrived (files read as fast as possible
wait for as long as it takes); a camera that has not delivered by then (its labels not even
in the queue: those are all taken in first) is left out of that fit (column `cameras`). With
a lag the row does not wait for them: the newest clock frame, once every older one has its
own fit, is fitted at once from what is in (`_fit_ahead`) and
the smoother gives the row `lag` frames back; the frame's own fit then replaces that one in
the smoother. A frame still waiting for its fit `BEHIND_S` after it arrived (the process
has too little CPU) gets no row and is counted: the rows never fall further
behind. Ctrl-C (`stop`) ends the run with every row so far written.
"""

from __future__ import annotations

import logging
import queue
import shutil
import threading
import time
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from mocap.core.calibration import Calibration
from mocap.core.machine import Machine
from mocap.core.tracks import Tracks, concatenate
from mocap.errors import InputError
from mocap.io.atomic import atomic_path
from mocap.io.cameras_toml import load_calibration, save_calibration
from mocap.io.machine_toml import load_machine
from mocap.io.session_toml import SessionCamera, SessionConfig, save_session_config
from mocap.io.tracks_csv import save_tracks
from mocap.live.feed import Feed
from mocap.live.pose import BASE_WINDOW, CameraHistory, FixedLagSmoother, WarmFit, warm_up
from mocap.live.rows import PoseWriter, row
from mocap.live.sources import FILE, SourceReader, SourceSpec
from mocap.reconstruct.kinfit import FitOptions
from mocap.tracking.model import CameraModel
from mocap.tracking.run import track_frames
from mocap.tracking.tracker import TrackOptions

log = logging.getLogger(__name__)

STALL_S = 1.0  # a clock camera silent this long hands the rows' clock to the next camera
BEHIND_S = 0.5  # a clock frame this long waiting for the fit (the process is starved of CPU) is skipped
FIRST_FRAME_S = 2.0  # the time a camera's first frame may take to be labelled (a search of the whole frame)
RESUME_S = 1.0  # a camera's frame this long after its last one (it was unplugged, its stream failed) is labelled afresh
_RESUME_WAIT_S = 30.0  # files read as fast as tracked: the longest a camera back after a gap waits for the rows to reach it


@dataclass(frozen=True)
class LiveRequest:
    """What `mocap live` was asked: paths as given; `lag` the smoother's lag in reference
    frames; `duration` seconds of the run (None: until the sources end or Ctrl-C); `feed`
    (host, port) or None; `record` a session folder to write, or None; `view` where the rows
    are shown as they come (`mocap.live.view.check_target`), or None; `choose_base` with a
    fixed base in `fit_options`: the base fitted per frame while the data say it moves
    (`WarmFit`; the test on the last `base_window` frames, None: on frames spread over the
    whole run), else held."""

    machine: str
    calibration: Path
    sources: tuple[SourceSpec, ...]
    out: Path
    realtime: bool = False
    duration: float | None = None
    lag: int = 1
    depth: int = 2
    wait_frames: float = 1.0
    feed: tuple[str, int] | None = None
    record: Path | None = None
    view: str | None = None
    follow_clocks: bool = False
    choose_base: bool = True
    base_window: int | None = BASE_WINDOW
    track_options: TrackOptions = field(default_factory=TrackOptions)
    fit_options: FitOptions = field(default_factory=FitOptions)


@dataclass(frozen=True)
class CameraCounts:
    """Frames `read` from the source, `out` tracked and handed to the fit, `dropped` late;
    `resumed` the gaps after which its labelling started afresh (`RESUME_S`)."""

    camera: str
    read: int
    out: int
    dropped: int
    reconnects: int
    resumed: int = 0


@dataclass(frozen=True)
class FrameAccount:
    """What became of the reference camera's frames: `read` from its source, each either a
    row (`rows`) or without one for a reason: `dropped` late at the source (the tracker
    behind), `unlabelled` (a first frame, or one after a gap, whose labelling failed; the
    next was tried), `skipped` (its fit more than `BEHIND_S` behind), `displaced` (labelled
    while another camera drove the rows), `unfinished` (read but not yet through when the
    run ended)."""

    camera: str
    read: int
    rows: int
    dropped: int = 0
    unlabelled: int = 0
    skipped: int = 0
    displaced: int = 0
    unfinished: int = 0

    REASONS = (("dropped", "dropped late"), ("unlabelled", "not labelled"), ("skipped", "skipped behind"),
               ("displaced", "while another camera drove the rows"), ("unfinished", "unfinished at the end"))

    def text(self) -> str:
        """"cam1's 600 frames: 592 rows, 8 dropped late" (the reasons that occurred)."""
        return f"{self.camera}'s {self.read} frames: {self.rows} rows" + "".join(
            f", {getattr(self, name)} {words}" for name, words in self.REASONS if getattr(self, name))


@dataclass(frozen=True)
class LiveReport:
    rows: int
    cameras: tuple[CameraCounts, ...]
    latency_ms: np.ndarray
    lag_ms: float
    interrupted: bool
    skipped: int = 0
    feed: str | None = None
    view_ms: float = float("nan")  # the main thread's time per row handing it to the viewer
    view_dropped: int = 0  # rows not shown: the viewer's queue was full
    # followed cameras: (name, newest offset s, the camera's frame at the middle of its window, calibrated offset s)
    clocks: tuple[tuple[str, float, float, float], ...] = ()
    clock_update_ms: float = float("nan")  # CPU per re-estimate of the offsets
    # per row (R, 4) ms: the reference frame's tracking (arrival to its labels in the main thread), the wait
    # for the other cameras' frames, the fit, and the smoother's lag (the fit to the row written)
    stages_ms: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    reference: FrameAccount | None = None  # what became of the reference camera's frames
    rows_of_others: int = 0  # rows of other cameras' frames (while they drove the rows)
    # the tests of whether the base moves: (frames fitted then, it moves); their CPU time (ms) each
    base_tests: tuple[tuple[int, bool], ...] = ()
    base_test_ms: float = float("nan")

    def summary(self, out) -> str:
        """The run's one summary line."""
        counts = "; ".join(f"{c.camera} in {c.read} out {c.out} dropped {c.dropped}"
                           + (f" reconnected {c.reconnects}x" if c.reconnects else "")
                           + (f" labelled afresh {c.resumed}x after a gap" if c.resumed else "") for c in self.cameras)
        if len(self.latency_ms):
            p50, p99, worst = np.percentile(self.latency_ms, [50, 99]).tolist() + [float(self.latency_ms.max())]
            latency = f"latency p50 {p50:.0f} ms, p99 {p99:.0f} ms, max {worst:.0f} ms"
        else:
            latency = "latency -"
        return (f"{self.rows} rows to {out}; {counts}; {latency} (the smoother's lag of {self.lag_ms:.0f} ms "
                f"included)" + (f"; {self.reference.text()}" if self.reference is not None else "")
                + (f" (and {self.rows_of_others} rows of the other cameras' frames while they drove the rows)"
                   if self.rows_of_others else "")
                + (f"; {self.skipped} frames' rows skipped, more than {BEHIND_S:g} s behind (too little "
                                "CPU)" if self.skipped else "") + "".join(
                    f"; {name} clock offset {now:+.4f} s at its frame {at:.0f} (calibrated {then:+.4f} s)"
                    for name, now, at, then in self.clocks)
                + _base_text(self.base_tests)
                + (f"; {self.view_dropped} rows not shown in the viewer (it fell behind)" if self.view_dropped else "")
                + ("; interrupted" if self.interrupted else ""))


class CameraWorker(threading.Thread):
    """One camera's tracker (`track_frames`, the code of `mocap track`) fed frame by frame from
    its source; each frame's labels go to `labelled` as (camera index, time, arrived,
    pixels (M, 2)). A first frame that cannot be labelled is skipped and the next one tried.
    A frame more than `RESUME_S` after the one before (the camera was unplugged, its stream
    failed) is labelled afresh as a first frame, from the joints `resume(its time)` gives (the
    rows' fit nearest before it, None: `start`): the tracker's state of before the gap would
    follow the machine from where it was (a marker taken for another while it catches up). The
    gap is first told to the rows (a notice with no pixels, just before that frame's time):
    files read as fast as they are tracked wait for every camera's frames, and the rows could
    not pass the gap to reach that frame's time."""

    def __init__(self, k: int, reader: SourceReader, model: CameraModel, start: np.ndarray, fps: float,
                 options: TrackOptions, labelled: queue.Queue, stop: threading.Event, keep: bool = True,
                 resume=None):
        super().__init__(name=f"track {reader.spec.camera}", daemon=True)
        self.k, self.reader, self.model, self.start_joints, self.fps = k, reader, model, start, fps
        self.keep = keep  # the labels kept for `tracks()` (--record); else memory stays flat however long the run
        self.options, self.labelled, self.stop = options, labelled, stop
        self.markers = {name: m for m, name in enumerate(model.machine.marker_names)}
        self.resume = resume or (lambda: None)
        self.out = 0
        self.unlabelled = 0  # frames taken whose labelling as a first frame failed
        self.resumed = 0  # gaps after which the tracking started afresh
        self.parts: list[Tracks] = []
        self.finished = threading.Event()
        self._meta: dict[int, tuple[float, float]] = {}
        self._exhausted = False
        self._held = None  # the frame after a gap, for the next run of the tracker
        self._last = -np.inf  # the time of the last frame handed to the tracker

    def run(self) -> None:
        try:
            start = self.start_joints
            while not self._exhausted and not self.stop.is_set():
                try:
                    tracks, _ = track_frames(self.model, self._frames(), start, None, self.fps, self.options,
                                             on_frame=self._on_frame, keep=self.keep)
                    self.parts.append(tracks)
                except ValueError as exc:  # the first frame not labelled: try the next ones
                    self.unlabelled += len(self._meta)
                    self._meta.clear()
                    log.info("camera %s: %s; trying the next frame", self.reader.spec.camera, exc)
                if self._held is not None:  # a gap: the tracking starts afresh from the rows' joints there
                    now = self.resume(self._held.time)
                    start = self.start_joints if now is None else now
        except Exception as exc:  # one line; the traceback at debug level
            log.error("camera %s: tracking failed (%s: %s); the others carry on", self.reader.spec.camera,
                      type(exc).__name__, exc)
            log.debug("camera %s: tracking failed", self.reader.spec.camera, exc_info=True)
        finally:
            self.finished.set()

    def _frames(self):
        """The source's frames for one run of the tracker: it ends before a frame that comes
        after a gap (held for the next run)."""
        first = True
        while not self.stop.is_set():
            if self._held is not None:
                frame, self._held = self._held, None
            else:
                frame = self.reader.take()
            if frame is None:
                if self.reader.done:
                    break
                continue
            if not first and frame.time - self._last > RESUME_S:
                log.info("camera %s: no frame for %.1f s; its next one labelled afresh", self.reader.spec.camera,
                         frame.time - self._last)
                self._held = frame
                self.resumed += 1
                self.labelled.put((self.k, frame.time - 0.5 / self.fps, frame.arrived, None, None))  # nothing before
                return
            first = False
            self._last = frame.time
            self._meta[frame.index] = (frame.time, frame.arrived)
            yield frame.index, frame.gray
        self._exhausted = True

    def _on_frame(self, index: int, rows: Tracks) -> None:
        time_ref, arrived = self._meta.pop(index)
        pixels = np.full((len(self.markers), 2), np.nan)
        if len(rows):
            pixels[[self.markers[m] for m in rows.marker]] = rows.xy
        self.out += 1
        self.labelled.put((self.k, time_ref, arrived, pixels, time.perf_counter()))

    def tracks(self) -> Tracks | None:
        return concatenate(self.parts) if self.parts else None


def run_live(request: LiveRequest, stop: threading.Event | None = None, announce=None) -> LiveReport:
    """Run until every source has ended, `request.duration` has passed or `stop` is set.
    `announce(text)` is told where the feed listens, once it does."""
    stop = stop or threading.Event()
    machine = load_machine(request.machine)
    if machine.n_joints == 0:  # a rigid object: its pose per frame, and no link box hides its markers (`mocap fit`)
        request = replace(request, fit_options=replace(request.fit_options, base_motion=True),
                          track_options=replace(request.track_options, occlusion=False))
    calibration = load_calibration(request.calibration)
    order = _check_sources(request, calibration)
    cameras = [calibration.cameras[i] for i in order]
    fps = calibration.fps()[order]
    offsets = calibration.time_offsets[order]
    joints = calibration.joints(machine)
    start_joints = machine.clip_to_limits(np.zeros(machine.n_joints) if joints is None else joints)
    specs = {s.camera: s for s in request.sources}
    warm_up(machine, request.lag, _base_columns(request, machine))  # not in the first rows
    clock_start = time.perf_counter() + 0.2  # the threads started first
    readers = [SourceReader(specs[c.name], fps[k], offsets[k], clock_start, stop,
                            (offsets[k] - offsets.min()) if request.realtime else None, request.depth)
               for k, c in enumerate(cameras)]
    for reader, camera in zip(readers, cameras):
        if reader.size is not None and tuple(reader.size) != tuple(camera.size):
            raise InputError(f"--source {camera.name}: the video is {reader.size[0]}x{reader.size[1]} but the camera "
                             f"was calibrated at {camera.size[0]}x{camera.size[1]}; give the camera's own video",
                             path=reader.spec.target)
    labelled: queue.Queue = queue.Queue()
    workers = [CameraWorker(k, reader, CameraModel(machine, camera, solid=machine.n_joints > 0), start_joints,
                            fps[k], request.track_options, labelled, stop, keep=request.record is not None)
               for k, (reader, camera) in enumerate(zip(readers, cameras))]
    with ExitStack() as held:
        if request.record is not None:  # the folder held (one command writes it) and marked unfinished
            held.enter_context(_recording(request.record))
        feed = Feed(*request.feed) if request.feed is not None else None
        if feed is not None and announce is not None:
            announce(f"feed on {feed.url}")
        writer = PoseWriter(machine, request.out, _base_columns(request, machine))
        chosen = Calibration(tuple(cameras), tuple(calibration.extras[i] for i in order), calibration.metadata)
        view = _view(request.view, machine, chosen)
        follower = None
        if request.follow_clocks and len(cameras) > 1:
            from mocap.live.clocks import ClockFollower

            follower = ClockFollower(machine, cameras, fps, offsets, stop)
        loop = _Loop(request, machine, cameras, fps, workers, writer, feed, stop, view, follower)
        for worker in workers:  # after a gap a camera's labelling starts afresh from the rows' joints there
            worker.resume = lambda t, k=worker.k: loop.joints_at(k, t)
        with ExitStack() as videos:
            _recorders(request, readers, cameras, fps, videos)
            for thread in [*readers, *workers, *([follower] if follower is not None else [])]:
                thread.start()
            try:
                loop.run(clock_start)
            finally:
                stop.set()
                for thread in [*readers, *workers]:
                    thread.join(timeout=5.0)
                writer.close()
                if feed is not None:
                    feed.close()
                if view is not None:
                    view.close()
        if follower is not None:
            follower.finish()
        if request.record is not None:
            _record(request, machine, calibration, order, cameras, fps, workers)
    counts = tuple(CameraCounts(c.name, r.read, w.out, r.dropped, r.reconnects, w.resumed)
                   for c, r, w in zip(cameras, readers, workers))
    reference = FrameAccount(cameras[0].name, readers[0].read, loop.clocked[0] - loop.skipped_by[0], readers[0].dropped,
                             workers[0].unlabelled, loop.skipped_by[0], loop.displaced[0],
                             readers[0].read - readers[0].dropped - workers[0].unlabelled - loop.received[0])
    return LiveReport(
        loop.rows, counts, np.array(loop.latency), 1000.0 * request.lag / fps[0], loop.interrupted, loop.skipped,
        feed.url if feed is not None else None,
        view_ms=1000.0 * loop.view_s / loop.rows if view is not None and loop.rows else float("nan"),
        view_dropped=view.dropped if view is not None else 0,
        clocks=() if follower is None else tuple((c.name, follower.offset(k), follower.at[k], float(offsets[k]))
                                                 for k, c in enumerate(cameras) if k > 0),
        clock_update_ms=1000.0 * follower.cpu_s / follower.updates if follower is not None and follower.updates
        else float("nan"), stages_ms=np.array(loop.stages).reshape(-1, 4), reference=reference,
        rows_of_others=sum(c - s for c, s in zip(loop.clocked[1:], loop.skipped_by[1:])),
        base_tests=tuple(loop.fit.base_tests),
        base_test_ms=1000.0 * loop.fit.base_test_s / len(loop.fit.base_tests) if loop.fit.base_tests else float("nan"))


def _base_columns(request: LiveRequest, machine: Machine) -> bool:
    """Whether the rows carry the base's pose: fitted per frame, or chosen from the data."""
    return request.fit_options.base_motion or (request.choose_base and machine.n_joints > 0)


def _base_text(tests) -> str:
    """"; the base fitted per frame (3 tests, its choice changed 1x)" or ''."""
    if not tests:
        return ""
    changes = sum(a[1] != b[1] for a, b in zip(((0, True),) + tuple(tests[:-1]), tests))  # fitted per frame until the first
    return (f"; the base {'fitted per frame' if tests[-1][1] else 'held where the calibration saw it'} "
            f"({len(tests)} tests of its motion, the choice changed {changes}x)")


def _view(target: str | None, machine: Machine, calibration: Calibration):
    if target is None:
        return None
    from mocap.live.view import LiveView, live_blueprint, open_stream

    from mocap.live.view import ViewThread

    view = ViewThread(LiveView(open_stream(target, live_blueprint(machine)), machine, calibration))
    view.start()
    return view


class _Loop:
    """The main thread's work: labelled frames in, rows out."""

    def __init__(self, request, machine, cameras, fps, workers, writer, feed, stop, view=None, follower=None):
        self.request, self.machine, self.cameras, self.fps = request, machine, cameras, fps
        self.workers, self.writer, self.feed, self.stop, self.view = workers, writer, feed, stop, view
        self.view_s = 0.0
        self.follower = follower
        self.patient = not request.realtime and all(w.reader.spec.kind == FILE for w in workers)
        # files read as fast as they are tracked: a camera may run any way ahead of the rows, its frames kept
        self.history = [CameraHistory(f, depth=None if self.patient else 256) for f in fps]
        self.fit = WarmFit(machine, cameras, request.fit_options, choose_base=request.choose_base,
                           base_window=request.base_window)
        self.smoother = FixedLagSmoother(machine, request.lag, base_motion=_base_columns(request, machine))
        # clock frames waiting: (frame, time, arrived, labels in, the camera whose frame it is)
        self.pending: list[tuple[int, float, float, float, int]] = []
        self.waiting: list[tuple[int, float, float, list[str], object, tuple]] = []  # fitted, awaiting the smoother
        self.last_frame = -1
        self.ahead = -1  # the clock frame fitted ahead of its cameras (`_fit_ahead`)
        self.rows = self.skipped = 0
        n_cameras = len(cameras)
        # per camera: labelled frames taken in, those that became clock frames, those of them
        # skipped (too far behind), and those that came while another camera drove the rows
        self.received, self.clocked, self.skipped_by, self.displaced = ([0] * n_cameras for _ in range(4))
        self.joints_now: np.ndarray | None = None  # the newest fit's joints (a camera back after a gap starts there)
        self.time_now = -np.inf  # ... and its time on the reference clock
        self.latency: list[float] = []
        self.stages: list[tuple[float, float, float, float]] = []
        self.interrupted = False
        self.seen: list[float] = []  # when each camera last delivered labels
        self.patient = not request.realtime and all(w.reader.spec.kind == FILE for w in workers)
        # with a lag, the newest frame fitted ahead gives the row `lag` back at once (files read as fast as
        # they are tracked wait for every frame instead)
        self.early = request.lag > 0 and not self.patient

    def run(self, clock_start: float) -> None:
        end = None if self.request.duration is None else clock_start + self.request.duration
        # a camera counts as delivering until its first frame is due and has had time to be labelled
        self.seen = [clock_start + (w.reader.pace or 0.0) + FIRST_FRAME_S for w in self.workers]
        labelled = self.workers[0].labelled
        while True:
            if self.stop.is_set():
                self.interrupted = True
                break
            if end is not None and time.perf_counter() >= end:
                break
            try:
                item = labelled.get(timeout=0.05)
            except queue.Empty:
                if all(w.finished.is_set() for w in self.workers) and labelled.empty():
                    self._emit(final=True)
                    break
                self._emit()
                continue
            self._take(*item)
            # the labels already queued are taken in before any frame is judged late: a main thread
            # behind (short of CPU) read a reference frame's labels and found the other cameras'
            # of its time missing while they sat in the queue behind it (rows fitted without them)
            for _ in range(labelled.qsize()):
                try:
                    self._take(*labelled.get_nowait())
                except queue.Empty:
                    break
            self._emit()
        self._emit(final=True)  # the frames still waiting for a camera: with those there are
        for pose_and_meta in self._drain():
            self._write(*pose_and_meta)

    def _take(self, k: int, time_ref: float, arrived: float, pixels: np.ndarray | None, labelled_at: float) -> None:
        """Camera `k`'s labels of its frame at `time_ref` into its history (a clock frame's
        also among those waiting for their fit); `pixels` None: its notice of a gap, nothing
        from it until after `time_ref`."""
        if pixels is None:
            self.history[k].add(time_ref, np.full((len(self.machine.marker_names), 2), np.nan))
            return
        if self.follower is not None:  # the frame placed with its camera's newest offset
            index = int(round((time_ref - self.follower.calibrated[k]) * self.fps[k]))
            self.follower.add(k, index, pixels)
            time_ref = index / self.fps[k] + self.follower.offset(k)
        self.history[k].add(time_ref, pixels)
        self.seen[k] = time.perf_counter()
        clock = self._clock()  # before this frame counts as taken in: a camera's last frame is still its own
        self.received[k] += 1
        frame = int(round(time_ref * self.fps[0]))
        if k == clock and frame > self.last_frame and (not self.pending or frame > self.pending[-1][0]):
            self.pending.append((frame, frame / self.fps[0], arrived, labelled_at, k))
            self.clocked[k] += 1
        else:
            self.displaced[k] += 1

    def joints_at(self, k: int, t: float) -> np.ndarray | None:
        """The joints for camera `k`'s frame at `t` after a gap: the newest fit's (live, the
        rows are at now); with files read as fast as they are tracked, once the rows have
        reached the last reference frame before `t` (a camera's tracker may run far ahead of
        the rows), or after `_RESUME_WAIT_S`."""
        if self.patient and k != self._clock():
            waited = time.perf_counter()
            reach = t - 0.5 / self.fps[k] - 1.0 / self.fps[0] - 1e-6  # the notice's time, a reference frame back
            while (self.time_now < reach and not self.stop.is_set()
                   and time.perf_counter() - waited < _RESUME_WAIT_S):
                time.sleep(0.005)
        return self.joints_now

    def _clock(self) -> int:
        """The camera whose frames make the rows: the first not finished (its tracker ended and
        its labels all taken in) and, unless files are read as fast as they are tracked, that
        delivered within `STALL_S`."""
        now = time.perf_counter()
        for k, worker in enumerate(self.workers):
            if self._ended(k):
                continue
            if self.patient or now - self.seen[k] < STALL_S:
                return k
        return 0

    def _ended(self, k: int) -> bool:
        """Camera `k`'s tracker has ended and its labels are all taken in."""
        worker = self.workers[k]
        return worker.finished.is_set() and self.received[k] >= worker.out

    def _emit(self, final: bool = False) -> None:
        """Fit the waiting clock frames whose cameras are all in (or waited for long enough)."""
        now = time.perf_counter()
        while self.pending:
            frame, t, arrived, labelled_at, k = self.pending[0]
            ready = final
            if not ready:
                late = not self.patient and now > arrived + self.request.wait_frames / self.fps[0]
                ready = late or all(h.latest >= t or self._ended(j) for j, h in enumerate(self.history))
            if not ready:
                break
            self.pending.pop(0)
            if not self.patient and now - arrived > BEHIND_S:
                if frame != self.ahead:
                    self.skipped += 1  # the rows fall behind: this one is left out, not the next ones delayed
                    self.skipped_by[k] += 1
                continue
            self._fit(frame, t, arrived, (labelled_at, time.perf_counter()))  # the frames fitted before it: its wait
        if self.early and self.pending and self.pending[-1][0] != self.ahead and self.fit.warm:
            self._fit_ahead(*self.pending[-1][:4])

    def _pixels(self, t: float) -> tuple[np.ndarray, list[str]]:
        """(C, M, 2) every camera's pixels at `t` and the cameras that see a marker."""
        views = [h.pixels_at(t) for h in self.history]
        n_markers = len(self.machine.marker_names)
        pixels = np.stack([np.full((n_markers, 2), np.nan) if v is None else v for v in views])
        return pixels, [c.name for c, v in zip(self.cameras, views) if v is not None and np.isfinite(v[:, 0]).any()]

    def _fit(self, frame: int, t: float, arrived: float, stamps: tuple[float, float]) -> None:
        """`stamps`: when the frame's labels came, when the other cameras' were all in."""
        pixels, used = self._pixels(t)
        fitted = self.fit(pixels)
        if fitted.valid and self.machine.n_joints:
            self.joints_now = self.machine.clip_to_limits(fitted.values[: self.machine.n_joints])
        self.time_now = t
        for history in self.history:
            history.forget(t)
        self.last_frame = frame
        entry = (frame, t, arrived, used, fitted, (*stamps, time.perf_counter()))
        if frame == self.ahead:  # its row was given already: the frame's own fit replaces the provisional one
            self.smoother.revise(fitted)
            if self.waiting and self.waiting[-1][0] == frame:
                self.waiting[-1] = entry[:5] + (self.waiting[-1][5],)
            return
        self.waiting.append(entry)
        pose = self.smoother.push(t, fitted)
        if pose is not None:
            self._write(*self.waiting.pop(0), pose)

    def _fit_ahead(self, frame: int, t: float, arrived: float, labelled_at: float) -> None:
        """The newest clock frame fitted at once from what is in (the cameras whose frame after
        it has not come extrapolated, `CameraHistory.pixels_at`) and pushed to the smoother,
        which gives the row `lag` frames back without waiting; the frame's own fit revises it
        once its cameras are in."""
        if self.pending[0][0] != frame:  # an older frame still waits: this one's turn comes after
            return
        began = time.perf_counter()
        pixels, used = self._pixels(t)
        fitted = self.fit(pixels, keep=False)
        self.ahead = frame
        self.waiting.append((frame, t, arrived, used, fitted, (labelled_at, began, time.perf_counter())))
        pose = self.smoother.push(t, fitted)
        if pose is not None:
            self._write(*self.waiting.pop(0), pose)

    def _drain(self):
        for pose in self.smoother.flush():
            yield *self.waiting.pop(0), pose

    def _write(self, frame, t, arrived, used, fitted, stamps, pose) -> None:
        written = time.perf_counter()
        latency = 1000.0 * (written - arrived)
        labelled_at, ready, fitted_at = stamps
        self.stages.append(tuple(1000.0 * np.diff([arrived, labelled_at, ready, fitted_at, written])))
        values = row(self.machine, frame, t, latency, used, pose, fitted.rms_px, fitted.observations)
        self.writer.write(values)
        if self.feed is not None:
            self.feed.send(values)
        if self.view is not None:
            began = time.perf_counter()
            self.view.submit(frame, t, pose)
            self.view_s += time.perf_counter() - began
        self.rows += 1
        self.latency.append(latency)


def _check_sources(request: LiveRequest, calibration: Calibration) -> np.ndarray:
    """The calibration's indices of the sources' cameras, in the calibration's order."""
    names = [s.camera for s in request.sources]
    doubled = sorted({n for n in names if names.count(n) > 1})
    if doubled:
        raise InputError(f"--source {doubled[0]} is given twice; one source per camera")
    unknown = [n for n in names if n not in calibration.names]
    if unknown:
        raise InputError(f"--source {unknown[0]}: no such camera in the calibration (it has "
                         f"{', '.join(calibration.names)})", path=request.calibration)
    return np.array(sorted(calibration.names.index(n) for n in names))


def _recorders(request: LiveRequest, readers: list[SourceReader], cameras, fps, stack: ExitStack) -> None:
    """With --record, each device or stream's frames re-encoded as they come into
    DIR/videos/<camera>.mp4 (closed with `stack`); files are copied at the end."""
    if request.record is None:
        return
    from mocap.synthetic.encode import video_writer

    for reader, camera, rate in zip(readers, cameras, fps):
        if reader.spec.kind != FILE:
            write = stack.enter_context(video_writer(request.record / "videos" / f"{camera.name}.mp4",
                                                     tuple(camera.size), rate))
            reader.on_frame = lambda gray, write=write: write(cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR))


@contextmanager
def _recording(root: Path):
    """Hold the --record folder while the run writes it: its lock (`mocap.io.lock`; another
    command writing it is refused, a killed one's lock taken over), and no session.toml in it
    until every other file of this run is written (`_record` writes it last): a run killed
    part-way leaves no session that looks whole, with files of two runs."""
    from mocap.io.lock import folder_lock

    root.mkdir(parents=True, exist_ok=True)
    with folder_lock(root, f"mocap live --record {root}"):
        (root / "session.toml").unlink(missing_ok=True)
        yield


def _copy(source: str | Path, target: Path) -> None:
    """`source` copied to `target` whole or not at all (written beside it, then renamed)."""
    with atomic_path(target) as tmp:
        shutil.copyfile(source, tmp)


def _record(request: LiveRequest, machine: Machine, calibration: Calibration, order, cameras, fps, workers) -> None:
    """The session folder for the offline chain: session.toml, calibration/cameras.toml,
    calibration/labels.csv (each camera's first labelled frame), videos/<camera>.mp4 (a file
    copied; a device or stream recorded as it came) and tracks/<camera>.csv (the live
    tracker's labels). Every file is written whole or not at all, session.toml last."""
    root = request.record
    root.mkdir(parents=True, exist_ok=True)
    machine_ref = request.machine
    if Path(request.machine).is_file():
        _copy(request.machine, root / "machine.toml")
        machine_ref = "machine.toml"
    entries, first_labels = [], []
    for k, camera in enumerate(cameras):
        spec = workers[k].reader.spec
        video = f"videos/{camera.name}.mp4"
        if spec.kind == FILE:
            _copy(spec.target, root / video)
        entries.append(SessionCamera(camera.name, video, float(fps[k])))
        tracks = workers[k].tracks()
        if tracks is not None and len(tracks):
            save_tracks(tracks, root / "tracks" / f"{camera.name}.csv")
            first_labels.append(tracks.select(tracks.frame == tracks.frame.min()))
    if first_labels:  # the calibration frame's labels `mocap run` starts from: each camera's first frame
        save_tracks(concatenate(first_labels), root / "calibration" / "labels.csv")
    chosen = Calibration(tuple(calibration.cameras[i] for i in order), tuple(calibration.extras[i] for i in order),
                         calibration.metadata)
    save_calibration(chosen, root / "calibration" / "cameras.toml")
    save_session_config(SessionConfig(machine_ref, tuple(entries), {"calibration_frame": 0},
                                      {"recorded_by": "mocap live"}), root / "session.toml")
