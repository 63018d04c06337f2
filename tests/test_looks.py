"""Looks of synthetic sessions: drawn from a seed, varied, rendered as set, written into
truth/scene.toml."""

from __future__ import annotations

import tomllib
from dataclasses import replace

import numpy as np
import pytest

from mocap.cli import main
from mocap.io.machine_toml import load_machine
from mocap.synthetic import make_session
from mocap.synthetic.effects import EffectOptions
from mocap.synthetic.looks import PAINTS, Look, random_look
from mocap.synthetic.render import CameraRenderer, RenderOptions


def test_random_looks_are_seeded_and_varied():
    assert random_look(np.random.default_rng(4)) == random_look(np.random.default_rng(4))
    looks = [random_look(np.random.default_rng(seed)) for seed in range(60)]
    assert len({look.name for look in looks}) > 10
    assert {look.paint for look in looks} == set(PAINTS.values())
    assert any(look.square_grey is None for look in looks) and any(look.disk_grey > 50 for look in looks)
    assert any(look.overcast == 1 for look in looks) and any(look.haze > 0 for look in looks)
    assert {look.crf for look in looks} >= {18, 33} and len({look.scale for look in looks}) == 3
    assert 0.1 < np.mean([look.rain > 0 for look in looks]) < 0.6 and any(look.glare > 0 for look in looks)
    assert any(look.people for look in looks) and any(look.trucks for look in looks)
    assert any(look.other_machine for look in looks) and not all(look.other_machine for look in looks)
    ratios = [look.disk_ratio for look in looks]
    assert min(ratios) < 0.5 and max(ratios) > 0.7


def test_look_guards():
    with pytest.raises(ValueError, match="disk_ratio must be"):
        Look(disk_ratio=0.95)
    with pytest.raises(ValueError, match="overcast must be"):
        Look(overcast=2.0)
    with pytest.raises(ValueError, match="rain must be 0..1, glare 0..0.6"):
        Look(glare=0.8)
    with pytest.raises(ValueError, match="rain must be 0..1"):
        Look(people=-1)
    with pytest.raises(ValueError, match="crf must be"):
        Look(crf=60)


@pytest.fixture(scope="module")
def scene():
    machine = load_machine("hitachi_ex3500")
    session = make_session(machine, "hitachi_ex3500", n_cameras=1, n_cycles=1, seed=2, size=(960, 540))
    truth = session.tracks.select((session.tracks.frame == 0) & (session.tracks.score >= 1))
    return session, truth


def picture(session, look: Look) -> np.ndarray:
    """Frame 0 in `look`, without the camera's effects, as grey levels (float)."""
    options = RenderOptions(effects=EffectOptions.none(), look=look)
    renderer = CameraRenderer(session, 0, options, np.random.default_rng(1))
    _, image = next(renderer.frames(np.array([0]), clean=True))
    return image.astype(float) @ np.array([0.114, 0.587, 0.299])


def test_markers_are_painted_as_the_look_says(scene):
    """Disk grey at each marker's centre; the disk's dark area grows with the disk ratio as
    its square; without squares, the ring around a disk on the painted links is the paint."""
    session, truth = scene
    machine = session.machine
    grey_disk = picture(session, Look(disk_grey=70.0, square_grey=200.0))
    x, y = np.round(truth.xy).astype(int).T
    assert np.allclose(grey_disk[y, x], 70.0, atol=3.0)
    areas = []
    for ratio in (0.45, 0.75):
        light = Look(disk_ratio=ratio, paint=PAINTS["white"], dark=(200.0, 200.0, 200.0), overcast=1.0)
        grey = picture(session, light)  # around the disks: only white squares and light paint
        areas.append([np.sum(grey[yy - 12:yy + 13, xx - 12:xx + 13] < 100) for xx, yy in zip(x, y)])
    ratio_of_areas = np.median(np.array(areas[1]) / np.maximum(areas[0], 1))
    assert abs(ratio_of_areas - (0.75 / 0.45) ** 2) < 0.5
    bare = picture(session, Look(paint=PAINTS["yellow"], square_grey=None, overcast=1.0))
    painted = np.isin(machine.marker_links[machine.marker_index(truth.marker)],
                      [machine.link_names.index(n) for n in ("house", "boom", "arm")])
    yellow = 0.75 * np.array(PAINTS["yellow"]) @ np.array([0.114, 0.587, 0.299])  # overcast: shade 0.75
    for xx, yy, on_paint in zip(x, y, painted):
        sides = [bare[yy, xx - 9:xx - 7], bare[yy, xx + 8:xx + 10]]  # where the square was
        # the paint, shaded 0.75 (overcast), the boom and arm 4 % lighter and darker than the house (one
        # side may be off the link's edge)
        if on_paint:
            assert any(np.all(np.abs(side / yellow - 1) < 0.07) for side in sides)
        else:
            assert all(np.all(side > 200) for side in sides)


def test_cli_writes_the_look_into_the_scene(tmp_path, capsys):
    out = tmp_path / "s"
    assert main(["synth", "--machine", "bobcat_225", "--cameras", "1", "--cycles", "1", "--seed", "9",
                 "--scale", "0.25", "--look", "random", "--no-video", "--out", str(out)]) == 0
    look = random_look(np.random.default_rng([9, 2]))
    assert f"look: {look.name}" in capsys.readouterr().out
    scene = tomllib.loads((out / "truth" / "scene.toml").read_text())
    assert scene["look"]["name"] == look.name and scene["look"]["paint"] == list(look.paint)
    assert scene["look"]["crf"] == look.crf
    assert scene["options"]["size"] == [round(1920 * 0.25 * look.scale), round(1080 * 0.25 * look.scale)]


@pytest.mark.parametrize("seed", [3, 12])
def test_tracking_holds_on_random_looks(seed):
    """A random look's first frames tracked without labels from the true calibration: the
    wholly visible markers labelled, none wrongly, centres to a fraction of a pixel."""
    check_tracking(random_look(np.random.default_rng(seed)), seed)


@pytest.mark.parametrize("element, seed", [
    (dict(rain=0.45), 3), (dict(glare=0.4), 12), (dict(people=5, trucks=2, other_machine=True), 3),
    (dict(people=5, trucks=2, other_machine=True, square_grey=None), 5),
    (dict(shadows=True, overcast=0.0, sun_elevation_deg=40.0, sun_azimuth_deg=0.0), 3)])
def test_tracking_holds_through_rain_glare_and_clutter(element, seed):
    """Each new element of a look at its strongest, over a random look: tracking as above. (The
    shadows' sun puts 10 of 75 wholly visible markers of frames 60, 66, ... 84 partly or wholly in
    a link's shadow.)"""
    check_tracking(replace(random_look(np.random.default_rng(seed)), **element), seed)


def check_tracking(look: Look, seed: int) -> None:
    from mocap.tracking import CameraModel, track_frames

    machine = load_machine("hitachi_ex3500")
    size = (round(960 * look.scale / 2) * 2, round(540 * look.scale / 2) * 2)
    session = make_session(machine, "hitachi_ex3500", n_cameras=1, n_cycles=1, seed=seed, size=size,
                           distortion=look.distortion, shake_deg=look.shake_deg, readout=look.readout)
    options = RenderOptions(effects=EffectOptions(look.noise, look.blur, look.exposure, look.dust), look=look)
    renderer = CameraRenderer(session, 0, options, np.random.default_rng(seed))
    frames = [(f, image @ np.array([0.114, 0.587, 0.299])) for f, image in renderer.frames(np.arange(60, 90))]
    frames = [(f, np.clip(np.round(g), 0, 255).astype(np.uint8)) for f, g in frames]
    field = session.cameras[0]
    tracks, _ = track_frames(CameraModel(machine, field.camera), frames, session.motion.joints[60], fps=field.fps)
    truth = session.tracks.select((session.tracks.frame >= 60) & (session.tracks.frame < 90))
    true_xy = {(int(f), m): (xy, s) for f, m, xy, s in zip(truth.frame, truth.marker, truth.xy, truth.score)}
    error = np.array([np.linalg.norm(xy - true_xy.get((int(f), m), (np.inf, 0))[0])
                      for f, m, xy in zip(tracks.frame, tracks.marker, tracks.xy)])
    whole = {key for key, (_, s) in true_xy.items() if s >= 1}
    found = {(int(f), m) for f, m in zip(tracks.frame, tracks.marker)}
    assert np.all(error < 2.0), look.name  # no wrong label
    assert len(found & whole) >= 0.9 * len(whole), look.name
    assert np.median(error) < 0.15, look.name


def seen(session, look: Look, frame: int = 0, seed: int = 1) -> np.ndarray:
    """Frame `frame` in `look` with its weather but no sensor effects, BGR as float."""
    renderer = CameraRenderer(session, 0, RenderOptions(effects=EffectOptions.none(), look=look),
                              np.random.default_rng(seed))
    _, image = next(renderer.frames(np.array([frame])))
    return image.astype(float)


def test_rain_streaks_light_thin_lines_that_change_from_frame_to_frame(scene):
    session, truth = scene
    dry = seen(session, Look())
    wet, again = seen(session, Look(rain=0.4)), seen(session, Look(rain=0.4))
    next_frame = seen(session, Look(rain=0.4), 1)
    assert np.array_equal(wet, again)  # seeded
    change = (wet - dry).sum(axis=-1)
    assert change.min() >= 0 and 0.005 < np.mean(change > 15) < 0.2  # lighter, in streaks only
    h, w = change.shape
    quarters = (change > 15).reshape(2, h // 2, 2, w // 2).mean(axis=(1, 3))
    assert quarters.min() > 0.2 * quarters.max()  # over the whole picture
    moved = np.abs((next_frame - seen(session, Look(), 1)).sum(axis=-1) - change) > 15
    assert moved.mean() > 0.5 * np.mean(change > 15)  # the streaks fall: another layer next frame


def test_glare_veils_the_picture_most_towards_the_sun(scene):
    session, truth = scene
    plain, glare = seen(session, Look()), seen(session, Look(glare=0.4))
    assert np.array_equal(glare, seen(session, Look(glare=0.4)))
    lift = (glare - plain).mean(axis=-1)
    assert lift.min() >= -1 and lift.mean() > 5
    share = lift / np.maximum(250.0 - plain.mean(axis=-1), 1.0)  # the veil's share where the picture was dark
    dim = plain.mean(axis=-1) < 200
    h = share.shape[0]
    top, bottom = share[: h // 3][dim[: h // 3]], share[-h // 3 :][dim[-h // 3 :]]
    assert np.median(top) > 1.3 * np.median(bottom)  # the sun is above the top edge
    x, y = np.round(truth.xy).astype(int).T
    grey_plain, grey_glare = plain[y, x].mean(axis=-1), glare[y, x].mean(axis=-1)
    assert np.all(grey_glare > grey_plain + 5)  # the disks' black lifted: less contrast


def test_clutter_stands_behind_the_machine(scene):
    """People, haul trucks and another machine change the backdrop but not a pixel of the
    machine's markers, and their dark round tyres and black-on-white sign are in view."""
    session, truth = scene
    plain = seen(session, Look())
    busy = seen(session, Look(people=5, trucks=2, other_machine=True))
    assert np.array_equal(busy, seen(session, Look(people=5, trucks=2, other_machine=True)))
    changed = np.abs(busy - plain).sum(axis=-1) > 30
    assert changed.mean() > 0.01
    x, y = np.round(truth.xy).astype(int).T
    for xx, yy in zip(x, y):
        assert not changed[yy - 3 : yy + 4, xx - 3 : xx + 4].any()
    dark = (busy.mean(axis=-1) < 40) & changed
    assert dark.sum() > 50  # tyres, the sign's disk, heads


def test_links_cast_hard_shadows_on_each_other(scene):
    """With the sun low beside the camera, shadows darken parts of the machine (never the
    backdrop) to the shaded level, and only where a sunlit face was; overcast casts none."""
    session, truth = scene
    sun = dict(sun_elevation_deg=30.0, sun_azimuth_deg=140.0)
    plain, shadowed = picture(session, Look(**sun)), picture(session, Look(shadows=True, **sun))
    assert np.array_equal(shadowed, picture(session, Look(shadows=True, **sun)))
    ratio = shadowed / np.maximum(plain, 1.0)
    dark = ratio < 0.9
    assert dark.mean() > 0.002 and ratio.max() < 1.02  # shadows only darken
    # inside a shadow (away from its anti-aliased edge), the level is shade(-1) / shade(facing): at
    # least the ambient 0.45 of full sun, at most what a face at the sun's grazing angle keeps
    core = cv2_erode(dark)
    assert core.sum() > 100 and np.all((ratio[core] > 0.45 - 0.02) & (ratio[core] < 0.9))
    plain_rows = np.flatnonzero(dark.any(axis=1))
    assert plain_rows.min() > 0.1 * dark.shape[0]  # on the machine, not the sky
    overcast = dict(overcast=1.0, **sun)
    assert np.array_equal(picture(session, Look(**overcast)), picture(session, Look(shadows=True, **overcast)))


def cv2_erode(mask: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
