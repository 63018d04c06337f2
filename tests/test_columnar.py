"""Columnar reading: the pyarrow reader agrees with the checked csv reader, and Parquet
round-trips tracks, points and motion."""

import numpy as np
import pyarrow.parquet as pq
import pytest

from mocap.core.motion import Motion
from mocap.core.points import Points
from mocap.core.tracks import Tracks
from mocap.errors import InputError
from mocap.io.machine_toml import load_machine
from mocap.io.motion_csv import load_motion, save_motion
from mocap.io.points_csv import load_points, save_points
from mocap.io import columnar
from mocap.io.tracks_csv import load_tracks, save_tracks

FIELDS = ("camera", "frame", "marker", "xy", "time", "score")


def random_tracks(rng, n_frames=50, with_time=True) -> Tracks:
    cameras = [f"cam {k}é" for k in range(rng.integers(1, 4))]
    markers = [f"M{k}" for k in range(rng.integers(1, 9))]
    c, f, m = np.meshgrid(np.arange(len(cameras)), np.arange(n_frames), np.arange(len(markers)), indexing="ij")
    keep = rng.random(c.size) < 0.7
    n = int(keep.sum())
    time = f.ravel()[keep] / 29.97 if with_time else None
    return Tracks.from_rows(np.array(cameras, dtype=object)[c.ravel()[keep]], f.ravel()[keep] + 3,
                            np.array(markers, dtype=object)[m.ravel()[keep]], rng.uniform(-200, 2200, (n, 2)),
                            time, np.where(rng.random(n) < 0.2, np.nan, rng.random(n)))


def assert_same(a: Tracks, b: Tracks, atol=0.0) -> None:
    for name in FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        if x.dtype == object:
            assert list(x) == list(y), name
        else:
            np.testing.assert_allclose(x, y, atol=atol, err_msg=name)


@pytest.mark.parametrize("seed", range(4))
def test_columnar_reading_equals_the_checked_reader(tmp_path, monkeypatch, seed):
    rng = np.random.default_rng(seed)
    tracks = random_tracks(rng, with_time=seed % 2 == 0)
    path = tmp_path / "tracks.csv"
    save_tracks(tracks, path)
    save_tracks(tracks, tmp_path / "tracks.parquet")
    fast, fast_parquet = load_tracks(path), load_tracks(tmp_path / "tracks.parquet")
    assert_same(fast, tracks, atol=5e-5)  # 4 decimals written
    with monkeypatch.context() as m:  # every value read as text and checked one by one
        m.setattr(columnar, "_typed", lambda *args: None)
        assert_same(fast, load_tracks(path))
        assert_same(fast_parquet, load_tracks(tmp_path / "tracks.parquet"))


def test_rows_are_named_by_their_line_past_blank_lines(tmp_path):
    """The fast read skips blank lines as the checked one does: a message names the row's
    own line (CRLF line ends too; lone CRs too, read the checked way)."""
    tracks = random_tracks(np.random.default_rng(1))
    save_tracks(tracks, tmp_path / "t.csv")
    lines = (tmp_path / "t.csv").read_text().splitlines()
    lines[6] = lines[6].replace(lines[6].split(",")[3], "2e6", 1)  # the 6th row's x far outside any image
    for end in ("\n", "\r\n"):
        (tmp_path / "b.csv").write_bytes(end.join(lines[:3] + ["", ""] + lines[3:] + [""]).encode())
        with pytest.raises(InputError, match=r"b.csv: line 9: pixel \(2e\+06, "):
            load_tracks(tmp_path / "b.csv")
    (tmp_path / "c.csv").write_bytes("\r".join(lines).encode())  # lines that end in a lone CR: the checked reader's
    with pytest.raises(InputError, match=r"c.csv: line 7: pixel \(2e\+06, "):
        load_tracks(tmp_path / "c.csv")


def test_one_file_per_camera_reads_as_one_file_of_them_all(tmp_path):
    """Per-camera files whose marker sets differ, read together: the same rows as the file of
    them all, the names kept as codes into their union (no name per row made)."""
    tracks = random_tracks(np.random.default_rng(5))
    paths = []
    for k, name in enumerate(tracks.cameras):
        own = tracks.of_camera(name)
        own = own.select(own.marker != tracks.markers[k % len(tracks.markers)])  # each lacks another marker
        paths.append(tmp_path / f"{k}.csv")
        save_tracks(own, paths[-1])
    together = load_tracks(paths)
    assert "camera" not in together.__dict__ and "marker" not in together.__dict__
    whole = tmp_path / "all.csv"
    save_tracks(together, whole)
    assert_same(together, load_tracks(whole))
    frames = together.frames
    np.testing.assert_array_equal(together.dense(tracks.cameras, tracks.markers, frames),
                                  load_tracks(whole).dense(tracks.cameras, tracks.markers, frames))


def test_names_that_need_quotes_are_written_quoted_and_read_back(tmp_path):
    tracks = random_tracks(np.random.default_rng(7))
    names = np.where(tracks.marker == tracks.marker[0], 'arm, "left"', tracks.marker)
    quoted = Tracks(tracks.camera, tracks.frame, names, tracks.xy, tracks.time, tracks.score)
    save_tracks(quoted, tmp_path / "t.csv")
    assert '"arm, ""left"""' in (tmp_path / "t.csv").read_text(encoding="utf-8")
    assert_same(load_tracks(tmp_path / "t.csv"), quoted, atol=5e-5)


@pytest.mark.parametrize("seed", range(3))
def test_tracks_parquet_round_trip(tmp_path, seed):
    tracks = random_tracks(np.random.default_rng(seed))
    save_tracks(tracks, tmp_path / "t.parquet")
    assert_same(load_tracks(tmp_path / "t.parquet"), tracks)
    save_tracks(tracks, tmp_path / "t.csv")
    assert_same(load_tracks(tmp_path / "t.csv"), load_tracks(tmp_path / "t.parquet"), atol=5e-5)


def test_parquet_tracks_are_checked_and_named_by_row(tmp_path):
    tracks = random_tracks(np.random.default_rng(5))
    bad = Tracks(tracks.camera, tracks.frame, tracks.marker, tracks.xy.copy(), tracks.time, tracks.score)
    bad.xy[7, 1] = np.inf
    save_tracks(bad, tmp_path / "bad.parquet")
    with pytest.raises(InputError, match=r"bad.parquet: row 8: x and y must be finite numbers"):
        load_tracks(tmp_path / "bad.parquet")
    (tmp_path / "junk.parquet").write_text("camera,frame\n")
    with pytest.raises(InputError, match="not a readable Parquet file"):
        load_tracks(tmp_path / "junk.parquet")
    with pytest.raises(InputError, match="file not found; check the tracks path"):
        load_tracks(tmp_path / "none.parquet")


def test_duplicates_across_a_parquet_and_a_csv_name_both_rows(tmp_path):
    tracks = random_tracks(np.random.default_rng(2))
    save_tracks(tracks, tmp_path / "a.parquet")
    save_tracks(tracks.select(np.arange(len(tracks)) == 4), tmp_path / "b.csv")
    with pytest.raises(InputError, match=r"a.parquet row 5 and .*b.csv line 2"):
        load_tracks([tmp_path / "a.parquet", tmp_path / "b.csv"])


def test_a_repeat_inside_one_of_several_files_is_named_by_that_file_alone(tmp_path):
    tracks = random_tracks(np.random.default_rng(3))
    save_tracks(tracks, tmp_path / "a.csv")
    save_tracks(tracks.select(np.r_[0, np.arange(len(tracks))]), tmp_path / "b.csv")  # every row of a, its first twice
    with pytest.raises(InputError, match=r"^.*b.csv: marker .* \(line 2 and line 3\); keep one row"):
        load_tracks([tmp_path / "a.csv", tmp_path / "b.csv"])


def test_points_parquet_round_trip_and_check(tmp_path):
    rng = np.random.default_rng(3)
    n = 40
    points = Points(np.arange(n) // 4, np.array([f"P{k % 4}" for k in range(n)], dtype=object),
                    rng.normal(size=(n, 3)), np.where(rng.random(n) < 0.3, np.nan, rng.random(n)),
                    rng.integers(2, 5, n))
    save_points(points, tmp_path / "p.parquet")
    back = load_points(tmp_path / "p.parquet")
    assert list(back.marker) == list(points.marker)
    np.testing.assert_array_equal(back.frame, points.frame)
    np.testing.assert_array_equal(back.xyz, points.xyz)
    np.testing.assert_array_equal(back.error_px, points.error_px)
    np.testing.assert_array_equal(back.views, points.views)
    points.xyz[3, 2] = np.nan
    save_points(points, tmp_path / "bad.parquet")
    with pytest.raises(InputError, match=r"row 4: x, y and z must be finite"):
        load_points(tmp_path / "bad.parquet")


def test_motion_parquet_round_trip_and_check(tmp_path):
    machine = load_machine("hitachi_ex3500")
    rng = np.random.default_rng(4)
    n, j, p = 30, len(machine.joint_names), len(machine.point_names)
    motion = Motion(machine.joint_names, machine.point_names, np.arange(n) * 2, np.arange(n) / 15.0,
                    rng.normal(size=(n, j)), rng.normal(size=(n, p, 3)), rng.normal(size=n),
                    joints_sd=np.abs(rng.normal(size=(n, j))), extra={"filled": (rng.random(n) < 0.5) * 1.0})
    save_motion(motion, machine, tmp_path / "m.parquet")
    back = load_motion(tmp_path / "m.parquet", machine)
    np.testing.assert_array_equal(back.frame, motion.frame)
    np.testing.assert_allclose(back.joints, motion.joints, rtol=1e-12)
    np.testing.assert_allclose(back.points, motion.points, rtol=1e-12)
    np.testing.assert_allclose(back.joints_sd, motion.joints_sd, rtol=1e-12)
    np.testing.assert_array_equal(back.extra["filled"], motion.extra["filled"])
    shuffled = Motion(**{**motion.__dict__, "frame": motion.frame[::-1].copy()})
    save_motion(shuffled, machine, tmp_path / "bad.parquet")
    with pytest.raises(InputError, match=r"row 2: frames must increase"):
        load_motion(tmp_path / "bad.parquet", machine)
    table = pq.read_table(tmp_path / "m.parquet")
    pq.write_table(table.drop_columns(["arm"]), tmp_path / "no_arm.parquet")
    with pytest.raises(InputError, match=r"header lacks arm \(is it the motion of"):
        load_motion(tmp_path / "no_arm.parquet", machine)


@pytest.mark.parametrize("seed", range(2))
def test_the_names_codes_a_reader_keeps_agree_with_the_names(tmp_path, seed):
    tracks = random_tracks(np.random.default_rng(seed), n_frames=30)
    save_tracks(tracks, tmp_path / "t.csv")
    for loaded in (load_tracks(tmp_path / "t.csv"), tracks):  # codes from the reader, or encoded
        order = lambda names: tuple(dict.fromkeys(names.tolist()))  # noqa: E731
        assert loaded.cameras == order(loaded.camera) and loaded.markers == order(loaded.marker)
        name = loaded.camera[-1]
        np.testing.assert_array_equal(loaded.rows_of_camera(name), loaded.camera == name)
        part = loaded.select(loaded.marker != loaded.marker[0])  # the codes carried over
        assert part.markers == order(part.marker) and loaded.marker[0] not in part.markers
        frames = np.arange(0, 40, 3)
        markers = ["M0", "nobody", *loaded.markers]
        np.testing.assert_array_equal(loaded.dense_of_camera(name, markers, frames),
                                      loaded.dense([name], markers, frames)[0])
        first, last = loaded.frame_span(name)
        np.testing.assert_array_equal(loaded.dense_of_camera(name, markers),
                                      loaded.dense([name], markers, np.arange(first, last + 1))[0])


def test_motion_csv_columnar_read_equals_the_checked_reader(tmp_path, monkeypatch):
    """The pyarrow read of a motion CSV gives the checked reader's Motion bit for bit; a row
    with a problem falls back to the checked reader, which names its line."""
    from mocap.io import motion_csv

    machine = load_machine("hitachi_ex3500")
    rng = np.random.default_rng(5)
    n, j, p = 40, len(machine.joint_names), len(machine.point_names)
    points = rng.normal(size=(n, p, 3))
    points[3, 0, 1] = np.nan  # an empty field
    motion = Motion(machine.joint_names, machine.point_names, np.arange(n) * 2, np.arange(n) / 15.0,
                    rng.normal(size=(n, j)), points, rng.normal(size=n), points_sd=np.abs(rng.normal(size=(n, p))),
                    extra={"filled": (rng.random(n) < 0.5) * 1.0, "base_x": rng.normal(size=n)})
    save_motion(motion, machine, tmp_path / "m.csv")
    assert motion_csv._read_columnar(tmp_path / "m.csv", lambda header, where: None) is not None
    fast = load_motion(tmp_path / "m.csv", machine)
    with monkeypatch.context() as m:
        m.setattr(motion_csv, "_read_columnar", lambda path, check_header: None)
        checked = load_motion(tmp_path / "m.csv", machine)
    for name in ("frame", "time", "joints", "points", "bucket_angle", "points_sd"):
        np.testing.assert_array_equal(getattr(fast, name), getattr(checked, name), err_msg=name)
    assert fast.extra.keys() == checked.extra.keys()
    for name in fast.extra:
        np.testing.assert_array_equal(fast.extra[name], checked.extra[name], err_msg=name)
    lines = (tmp_path / "m.csv").read_text().splitlines()
    lines[5] = "5" + lines[5][lines[5].index(","):]  # frame 8 becomes 5, after 6: frames no longer increase
    (tmp_path / "bad.csv").write_text("\n".join(lines[:3] + [""] + lines[3:]) + "\n")  # a blank line shifts the rest
    with pytest.raises(InputError, match=r"line 7: frames must increase"):
        load_motion(tmp_path / "bad.csv", machine)
