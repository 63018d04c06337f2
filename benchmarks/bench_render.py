"""Rendering speed of synthetic sessions at 1920x1080 on one core.

    python benchmarks/bench_render.py [--frames 300] [--machine hitachi_ex3500]

Prints frames/s of the renderer (clean pictures; with the camera's effects; with effects
and encoding to mp4v or H.264; clean and with effects under a rolling shutter reading the
rows over `--readout` of the frame interval) next to the reference: encoding a blank frame
with the same codec, and the ratio between the two.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from mocap.io.machine_toml import load_machine  # noqa: E402
from mocap.synthetic import make_session  # noqa: E402
from mocap.synthetic.effects import EffectOptions  # noqa: E402
from mocap.synthetic.encode import video_writer  # noqa: E402
from mocap.synthetic.render import CameraRenderer, RenderOptions  # noqa: E402


def rate(run, frames: int) -> float:
    start = time.perf_counter()
    run()
    return frames / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--machine", default="hitachi_ex3500")
    parser.add_argument("--readout", type=float, default=0.9, help="the rolling shutter's cases' readout")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    machine = load_machine(args.machine)
    sessions = {0.0: make_session(machine, args.machine, n_cameras=1, n_cycles=1, seed=7)}
    sessions[args.readout] = make_session(machine, args.machine, n_cameras=1, n_cycles=1, seed=7, readout=args.readout)
    session = sessions[0.0]
    camera = session.cameras[0]
    size = camera.camera.size
    frames = np.arange(camera.frames)[200 : 200 + args.frames]  # into the first dig
    n = len(frames)
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        rolling = f"rolling shutter {args.readout:g}"
        for label, clean, codec, readout in [
            ("render, clean", True, None, 0.0),
            ("render + effects", False, None, 0.0),
            ("render + effects + mp4v", False, "mp4v", 0.0),
            ("render + effects + h264", False, "h264", 0.0),
            (f"render, clean, {rolling}", True, None, args.readout),
            (f"render + effects, {rolling}", False, None, args.readout),
        ]:
            renderer = CameraRenderer(sessions[readout], 0, RenderOptions(effects=EffectOptions()),
                                      np.random.default_rng(1))

            def run(renderer=renderer, clean=clean, codec=codec):
                if codec is None:
                    for _ in renderer.frames(frames, clean=clean):
                        pass
                    return
                with video_writer(Path(tmp) / f"{codec}.mp4", size, camera.fps, codec, threads=1) as write:
                    for _, image in renderer.frames(frames, clean=clean):
                        write(image)

            results[label] = (rate(run, n), codec)
        blank = np.zeros((size[1], size[0], 3), np.uint8)
        reference = {}
        for codec in ("mp4v", "h264"):
            def run(codec=codec):
                with video_writer(Path(tmp) / f"blank_{codec}.mp4", size, camera.fps, codec, threads=1) as write:
                    for k in range(n):
                        blank[:8, :8] = k % 256
                        write(blank)

            reference[codec] = rate(run, n)

    print(f"{args.machine}, {size[0]}x{size[1]}, {n} frames, one core")
    print(f"{'case':44s} {'frames/s':>9s} {'blank encode':>13s} {'ratio':>7s}")
    for label, (fps, codec) in results.items():
        ref = reference.get(codec)
        print(f"{label:44s} {fps:9.1f} {'' if ref is None else f'{ref:13.1f}':>13s} "
              f"{'' if ref is None else f'{fps / ref:7.2f}':>7s}")
    for codec, fps in reference.items():
        print(f"{'blank frame + ' + codec:44s} {fps:9.1f}")


if __name__ == "__main__":
    main()
