"""The synth stage: plan a machine's dig cycles, place cameras, write the session folder
(session.toml, truth/, videos/) and return the summary."""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from mocap.errors import InputError
from mocap.io.machine_toml import load_machine, resolve_machine_path
from mocap.io.outputs import check_output_folder
from mocap.io.session import Session, mark_complete

log = logging.getLogger(__name__)

MAX_CYCLES = 100  # about an hour of digging


@dataclass(frozen=True)
class SynthRequest:
    """What `mocap synth` was asked for (its options, with the same defaults)."""

    machine: str
    out: Path
    cameras: int = 3
    cycles: int = 4
    seed: int = 7
    size: str = "1920x1080"
    classes: str = "1,2,3"
    distortion: bool = False
    shake: float = 0.0
    bounce: float = 1.0
    reactive: float = 1.0
    redirect: float = 0.4
    hold: float = 2.0
    scale: float = 1.0
    codec: str = "h264"
    noise: float = 2.5
    blur: float = 0.5
    exposure: float = 0.08
    dust: float = 0.55
    clean: bool = False
    rolling_shutter: float | None = None
    look: str = "default"
    no_video: bool = False
    fps: float = 30.0  # the first camera's; the others run at 1000/1001 of it


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--size {text!r}: expected WIDTHxHEIGHT, e.g. 1920x1080") from None
    if w < 64 or h < 64 or w > 7680 or h > 4320:
        raise InputError(f"--size {text!r}: from 64x64 to 7680x4320 pixels")
    return w, h


def parse_classes(text: str) -> tuple[str, ...]:
    from mocap.synthetic import CLASSES

    picks = [v.strip() for v in text.split(",") if v.strip()]
    if not picks or any(v not in ("1", "2", "3") for v in picks):
        raise InputError(f"--classes {text!r}: expected a comma list of 1, 2, 3")
    return tuple(CLASSES[int(v) - 1] for v in dict.fromkeys(picks))


# what `mocap synth` writes at a session folder's top (hidden: its lock and atomic temporaries)
_SYNTH_ENTRIES = frozenset({"session.toml", "machine.toml", "truth", "videos"})


def _interrupted_synth(out: Path) -> bool:
    """True for a folder an interrupted `mocap synth` left (killed at any moment): no COMPLETE,
    and nothing but what it writes; running it again finishes the folder."""
    entries = list(out.iterdir())
    return (not (out / "COMPLETE").exists()
            and all(p.name in _SYNTH_ENTRIES or p.name.startswith(".") for p in entries))


def run_synth(request: SynthRequest) -> str:
    """Write the synthetic session `request.out`; returns the summary."""
    from mocap.io.lock import check_free, folder_lock
    from mocap.synthetic import SessionOptions, make_session, summary, write_truth
    from mocap.synthetic.effects import EffectOptions
    from mocap.synthetic.looks import Look, random_look
    from mocap.synthetic.render import RenderOptions
    from mocap.synthetic.videos import render_videos

    machine_path = resolve_machine_path(request.machine)
    machine = load_machine(machine_path)
    if not 1 <= request.cameras <= 8:
        raise InputError(f"--cameras {request.cameras}: give 1 to 8 cameras")
    if not 1 <= request.cycles <= MAX_CYCLES:
        raise InputError(f"--cycles {request.cycles}: give 1 to {MAX_CYCLES} dig cycles")
    if not 0.0 <= request.redirect <= 1.0:
        raise InputError(f"--redirect {request.redirect}: a probability, give 0..1")
    if request.hold < 0.5:
        raise InputError(f"--hold {request.hold}: the machine must hold still at least 0.5 s")
    if not 5.0 <= request.fps <= 120.0:
        raise InputError(f"--fps {request.fps}: give a frame rate from 5 to 120")
    check_output_folder(request.out)
    if request.out.is_dir():
        check_free(request.out)  # another command writing the folder is named
    if request.out.exists() and not _interrupted_synth(request.out) and any(request.out.iterdir()):
        raise InputError("the output folder exists and is not empty; choose a new folder", path=request.out)
    if not 0.05 <= request.scale <= 4.0:
        raise InputError(f"--scale {request.scale}: give a factor between 0.05 and 4")
    width, height = parse_size(request.size)
    look = random_look(np.random.default_rng([request.seed, 2])) if request.look == "random" else Look()
    if request.rolling_shutter is not None:
        if not 0.0 <= request.rolling_shutter <= 0.9:
            raise InputError(f"--rolling-shutter {request.rolling_shutter}: give a share of the frame interval, 0..0.9")
        look = replace(look, readout=request.rolling_shutter)
    scale = request.scale * look.scale
    size = (max(16, round(width * scale)), max(16, round(height * scale)))
    try:
        if request.clean:
            effects = EffectOptions.none()
        elif request.look == "random":
            effects = EffectOptions(look.noise, look.blur, look.exposure, look.dust)
        else:
            effects = EffectOptions(request.noise, request.blur, request.exposure, request.dust)
    except ValueError as exc:
        raise InputError(f"{exc}; noise and exposure take 0..50, blur and dust 0..0.9") from None
    options = SessionOptions(
        n_cameras=request.cameras, n_cycles=request.cycles, seed=request.seed, size=size,
        distortion=request.distortion or look.distortion, shake_deg=request.shake or look.shake_deg, bounce=request.bounce,
        reactive=request.reactive,
        redirect_probability=request.redirect, classes=parse_classes(request.classes), hold=request.hold,
        readout=look.readout, fps=request.fps,
    )
    session = make_session(machine, str(request.machine), options)
    request.out.mkdir(parents=True, exist_ok=True)  # an interrupted earlier run's folder is written over
    with folder_lock(request.out, "mocap synth"):
        write_truth(session, request.out, machine_path, look)
        log.info("wrote the truth of %d cycles, %d cameras to %s", request.cycles, request.cameras, request.out)
        if not request.no_video:
            paths = render_videos(session, request.out, RenderOptions(codec=request.codec, effects=effects, look=look))
            log.info("wrote %d videos", len(paths))
        mark_complete(Session.open(request.out).complete_path, "mocap synth")
    lines = [summary(session)]
    if request.look == "random":
        lines.append(f"look: {look.name}")
    lines.append(f"wrote {request.out}" + ("" if request.no_video else f" with {request.codec} videos"))
    return "\n".join(lines)
