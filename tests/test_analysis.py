"""Dig-cycle analysis against the synthetic truth: cycles, dig bounds, classes,
redirections, scaling; guards; the command end to end."""

from __future__ import annotations

import tomllib
from dataclasses import replace
from functools import lru_cache

import numpy as np
import pytest

from mocap import cli
from mocap.analysis.core import FIRST, analyze
from mocap.analysis.features import ClassRules, classify
from mocap.analysis.score import planned_truth, score_analysis
from mocap.analysis.series import tip_series
from mocap.analysis.shape import build_templates, DigPaths
from mocap.analysis.similarity import group_digs
from mocap.core.ik import PlanarChain
from mocap.errors import InputError
from mocap.io.cycles_csv import load_cycle_table, save_cycle_table
from mocap.io.machine_toml import load_machine
from mocap.io.motion_csv import save_motion
from mocap.synthetic.machines import random_digger
from mocap.synthetic.motion import plan_session
from mocap.synthetic.paths import BACKHOE, CLASSES

SESSIONS = [("hitachi_ex3500", 3), ("hitachi_ex3500", 8), ("bobcat_225", 4), ("bobcat_225", 9)]


@lru_cache(maxsize=None)
def truth_session(name: str, seed: int, n: int = 6):
    machine = load_machine(name)
    plan = plan_session(machine, n, np.random.default_rng(seed))
    motion, truth = planned_truth(machine, plan)
    return machine, motion, truth


@lru_cache(maxsize=None)
def analysed(name: str, seed: int, n: int = 6):
    machine, motion, truth = truth_session(name, seed, n)
    return analyze(tip_series(motion)), truth


@pytest.mark.parametrize("name,seed", SESSIONS)
def test_every_cycle_found_with_its_dig_bounds_and_class(name, seed):
    a, truth = analysed(name, seed)
    score = score_analysis(a.table, truth)
    assert score.missed == 0 and score.extra == 0
    # min-jerk moves meet at rest for ~0.3 s either side of the true bound; reactive noise
    # (1 deg, 0.3 % of the reach) shifts the speed minimum by a fraction of that
    assert np.median(np.abs(score.start_errors)) < 0.5 and np.abs(score.start_errors).max() < 1.5
    assert np.median(np.abs(score.end_errors)) < 0.5 and np.abs(score.end_errors).max() < 1.5
    assert score.class_correct == score.true
    assert list(a.table)[: len(FIRST)] == list(FIRST)
    assert np.all(a.table["start_frame"] == a.table["dig_start_frame"])
    assert np.all(a.table["end_frame"][:-1] == a.table["start_frame"][1:] - 1)
    # the unsupervised grouping of the dig paths finds the three classes, no more
    assert a.grouping.count == 3
    assert all(len(set(a.table["class"][a.grouping.groups == g])) == 1 for g in range(1, 4))


def test_redirections_and_scales_over_sessions():
    # 12 cycles, four digs a class: with two, one dig's error is its classmate's too, the
    # scales being relative to the class's size
    tp = fp = fn = 0
    errors, redirected = [], []
    for name, seed in SESSIONS:
        a, truth = analysed(name, seed, 12)
        score = score_analysis(a.table, truth)
        tp, fp, fn = tp + score.redirect_tp, fp + score.redirect_fp, fn + score.redirect_fn
        errors.append(score.scale_errors)
        redirected.append(score.scale_redirected)
        found = a.table["redirection"] != "none"
        assert np.all(np.isfinite(a.table["redirection_time"][found]))
        inside = (a.table["redirection_time"] >= a.table["dig_start_time"]) & (
            a.table["redirection_time"] <= a.table["dig_end_time"])
        assert np.all(inside[found])
    assert tp / (tp + fp) >= 0.9 and tp / (tp + fn) >= 0.9, (tp, fp, fn)
    # the truth's scale is each dig's stretch against its class's general shape; what a
    # stretch cannot express of a dig's own push and rise is a few per cent; an operator's
    # kept lift is confounded with a vertical stretch as far as its fit is off, and a
    # missed or misjudged one moves its classmates' scales through the class's size (the
    # issue asks 95 % of all factors within 5 %; main's fit had 94.8 % here, this one 95.8 %)
    errors, redirected = np.abs(np.concatenate(errors)), np.concatenate(redirected)
    assert np.median(errors) < 0.015 and np.mean(errors <= 0.05) >= 0.95
    assert np.mean(errors[~redirected] <= 0.05) >= 0.95 and np.all(errors[~redirected] <= 0.1)


def test_vertical_scale_of_digs_with_a_kept_lift():
    # an operator's kept lift (1.5-3 % of the reach) on a steep rise lies almost along the
    # path: in arc length it reads as a taller dig (main's fit had these digs' vertical
    # factors 7-10 % off). With the event's own height taken out of the path in time, the
    # vertical factor of every dig whose kept redirection is found as kept is within 5 % of
    # the truth's (relative to the class's size, as the benchmark scores it)
    errors = []
    for seed in (1, 2, 7):
        a, truth = analysed("hitachi_ex3500", seed, 12)
        found = a.table["dig_start_time"]
        match = np.array([int(np.argmin(np.abs(found - t))) for t in truth["dig_start_time"]])
        assert np.all(np.abs(found[match] - truth["dig_start_time"]) < 1.0)
        ratio = a.table["scale_z"][match] / truth["scale_z"]
        labels = a.table["class"][match]
        kept = (truth["redirection"] == "kept") & (a.table["redirection"][match] == "kept")
        for label in np.unique(labels):
            pick = labels == label
            error = ratio[pick] / np.exp(np.median(np.log(ratio[pick]))) - 1.0
            errors.append(error[kept[pick]])
    errors = np.abs(np.concatenate(errors))
    assert len(errors) >= 4 and np.all(errors <= 0.05), errors


def test_vertical_scale_of_backhoe_digs_with_a_kept_lift():
    # a backhoe dig rises about a twelfth of the reach, so a kept lift off by 0.4 % of the
    # reach moves its vertical factor by 5 %; judged over the whole path (a backhoe dig has no
    # floor push bending into its rise inside the event's window, which a shovel dig's
    # window holds), the lift leaves the factors of the Bobcat's kept-lift digs 5.8 % off at
    # the median, 38 % at worst (the window left out: 8.2 % and 107 %)
    machine, errors = load_machine("bobcat_225"), []
    for seed in range(12):
        motion, truth = planned_truth(machine, plan_session(machine, 12, np.random.default_rng(seed), classes=(BACKHOE,)))
        a = analyze(tip_series(motion))
        found = a.table["dig_start_time"]
        match = np.array([int(np.argmin(np.abs(found - t))) for t in truth["dig_start_time"]])
        ratio = a.table["scale_z"][match] / truth["scale_z"]
        kept = (truth["redirection"] == "kept") & (a.table["redirection"][match] == "kept")
        errors.append((ratio / np.exp(np.median(np.log(ratio))) - 1.0)[kept])  # all digs are `other`: one class
    errors = np.abs(np.concatenate(errors))
    assert len(errors) >= 12
    assert np.median(errors) < 0.07 and errors.max() < 0.5, errors


def test_redirection_lift_reported_against_the_class_template():
    # the truth's operator lifts and lowers the tip by 1.5-3 % of the reach; the lift
    # reported is the height that lets the class template fit the dig best (a temporary
    # one judged over its window too), not the event fitted to the height about a quintic
    # in time, which the floor push's bend into the rise bends too (its median here was
    # 0.4 % of the reach, its 90th percentile 3.2 %, its worst 8 %: a kept lift read as a
    # lower; this fit's are 0.5, 1.6 and 3.5 %; over table 5's 120 sessions its median is
    # 0.3-0.5 % against 0.75-0.8 %)
    errors = []
    for name, seed in SESSIONS:
        a, truth = analysed(name, seed, 12)
        machine, _, _ = truth_session(name, seed, 12)
        reach = float(np.linalg.norm(PlanarChain.from_machine(machine).offsets, axis=1).sum())
        score = score_analysis(a.table, truth)
        errors.append(np.abs(score.lift_errors) / reach)
        found = a.table["redirection"] != "none"
        words = a.table["redirection_kind"][found]
        lift = a.table["redirection_lift_m"][found]
        assert all(("lift" in w) <= (v > 0) and ("lower" in w) <= (v < 0) for w, v in zip(words, lift))
    errors = np.concatenate(errors)
    # half the smallest lift at the median, less than the smallest lift itself at the 90th
    assert len(errors) >= 12 and np.median(errors) < 0.0075 and np.percentile(errors, 90) < 0.02, errors


def test_scale_fit_recovers_exact_stretches():
    s = np.linspace(0, 1, 64)
    template = np.column_stack([4 * s, 3 * s**2, np.radians(60 * s - 20)])
    scales = np.array([[1.0, 1.0], [0.8, 0.8], [1.1, 0.9], [0.9, 1.2]])
    paths = np.stack([np.column_stack([template[:, :2] * k, template[:, 2]]) for k in scales])
    # resample each stretched path at even arc length, as the analysis does
    for k in range(len(paths)):
        step = np.concatenate([[0], np.cumsum(np.hypot(*np.diff(paths[k, :, :2], axis=0).T))])
        u = step / step[-1]
        fine = np.linspace(0, 1, 2000)
        dense = np.column_stack([np.interp(fine, s, paths[k, :, d]) for d in range(3)])
        step = np.concatenate([[0], np.cumsum(np.hypot(*np.diff(dense[:, :2], axis=0).T))])
        u = step / step[-1]
        paths[k] = np.column_stack([np.interp(s, u, dense[:, d]) for d in range(3)])
    labels = np.array(["Type 1"] * 4, dtype=object)
    _, fitted = build_templates(DigPaths(s, paths), labels, np.zeros((4, 3)))
    expected = scales / np.exp(np.log(scales).mean(axis=0))
    np.testing.assert_allclose(fitted, expected, rtol=0.01)


def test_class_rules():
    rules = ClassRules()
    assert classify(0.1, -30, 5, 4, rules)[0] == "Type 1"
    assert classify(0.1, 2, 5, 4, rules)[0] == "Type 2"
    assert classify(0.5, -2, 2, 4, rules)[0] == "Type 3"
    assert classify(0.5, -30, 2, 4, rules)[0] == "other"
    assert classify(0.9, 0, 2, 4, rules)[0] == "other"
    label, why = classify(0.1, -30, -3, 2, rules)
    assert label == "other" and "not a front shovel" in why
    with pytest.raises(ValueError, match="base_ratio"):
        ClassRules(base_ratio=0.8, top_ratio=0.5)


def test_grouping_finds_separated_groups_and_none_in_one_blob():
    rng = np.random.default_rng(0)
    centres = np.array([[0, 0], [10, 0], [0, 10]])
    points = np.concatenate([c + rng.normal(0, 0.5, (8, 2)) for c in centres])
    d = np.linalg.norm(points[:, None] - points[None], axis=-1)
    g = group_digs(d)
    assert g.count == 3
    assert all(len(np.unique(g.groups[k * 8:(k + 1) * 8])) == 1 for k in range(3))
    with_outlier = np.concatenate([points, [[30.0, 30.0]]])
    g = group_digs(np.linalg.norm(with_outlier[:, None] - with_outlier[None], axis=-1))
    assert g.count == 3 and g.groups[-1] == 0 and np.all(g.groups[:-1] > 0)
    blob = rng.normal(0, 1, (20, 2))
    assert group_digs(np.linalg.norm(blob[:, None] - blob[None], axis=-1)).count == 1


def _with(motion, keep=None, **changes):
    if keep is not None:
        fields = {"frame": motion.frame[keep], "time": motion.time[keep], "joints": motion.joints[keep],
                  "points": motion.points[keep], "bucket_angle": motion.bucket_angle[keep],
                  "extra": {k: v[keep] for k, v in motion.extra.items()}}
        motion = replace(motion, **fields)
    return replace(motion, **changes)


def test_gaps_noise_and_partial_cycles():
    machine, motion, truth = truth_session("hitachi_ex3500", 3)
    rng = np.random.default_rng(1)
    points = motion.points + rng.normal(0, 0.02, motion.points.shape)  # 2 cm of reconstruction noise
    angle = motion.bucket_angle + np.radians(rng.normal(0, 0.2, len(motion)))
    gap = (motion.time > truth["dig_start_time"][2] + 2) & (motion.time < truth["dig_start_time"][2] + 3)
    points[gap] = np.nan
    angle[gap] = np.nan
    # a fit that flipped the bucket for half a second in the middle of the fourth dig
    flip = np.flatnonzero(motion.time > 0.5 * (truth["dig_start_time"][3] + truth["dig_end_time"][3]))[:15]
    angle[flip] += np.radians(150.0)
    filled = np.zeros(len(motion))
    filled[(motion.time > truth["dig_end_time"][3]) & (motion.time < truth["dig_end_time"][3] + 1)] = 1
    # the data begin in the middle of the first dig and end in the middle of the last
    keep = (motion.time > 0.5 * (truth["dig_start_time"][0] + truth["dig_end_time"][0])) & (
        motion.time < 0.5 * (truth["dig_start_time"][-1] + truth["dig_end_time"][-1]))
    noisy = _with(_with(motion, points=points, bucket_angle=angle, extra={"filled": filled}), keep)
    a = analyze(tip_series(noisy))
    inner = {k: v[1:-1] for k, v in truth.items()}
    cut = a.table["class_rule"] == "dig cut by the start or end of the data"
    assert cut[0] and cut[-1] and np.all(a.table["class"][cut] == "other") and np.all(a.table["complete"][cut] == 0)
    score = score_analysis({k: v[~cut] for k, v in a.table.items()}, inner)
    assert score.missed == 0 and score.extra == 0 and score.class_correct == score.true
    assert np.abs(score.start_errors).max() < 1.5 and np.abs(score.end_errors).max() < 1.5
    row = np.argmin(np.abs(a.table["dig_start_time"] - truth["dig_start_time"][2]))
    assert a.table["gap_frames"][row] >= 25 and a.table["gap_frames"][row + 1] >= 25 + 15
    assert a.table["redirection"][row + 1] == truth["redirection"][3] or truth["redirection"][3] != "none"


def test_pause_before_the_dig_moves_its_start_to_the_end_of_the_pause():
    machine, motion, truth = truth_session("hitachi_ex3500", 8)
    k = int(np.searchsorted(motion.time, truth["dig_start_time"][2]))
    hold = 150  # 5 s at 30 fps resting at the face
    index = np.concatenate([np.arange(k), np.full(hold, k), np.arange(k, len(motion))])
    paused = _with(motion, index)
    paused = replace(paused, frame=np.arange(len(index)), time=np.arange(len(index)) / 30.0)
    a = analyze(tip_series(paused))
    shifted = dict(truth)
    shifted["dig_start_time"] = truth["dig_start_time"] + np.where(np.arange(len(truth["class"])) >= 2, hold / 30, 0)
    shifted["dig_end_time"] = truth["dig_end_time"] + np.where(np.arange(len(truth["class"])) >= 2, hold / 30, 0)
    score = score_analysis(a.table, shifted)
    assert score.missed == 0 and score.extra == 0
    assert np.abs(score.start_errors).max() < 1.5


def test_a_dig_that_rests_before_its_lift_out_ends_where_it_comes_to_rest():
    # the bucket rests 1.5-2.5 s at the end of every dig (bouncing with the base), then
    # lifts out: the dig ends where it came to rest, not at the lift-out (2 s later)
    machine = load_machine("hitachi_ex3500")
    plan = plan_session(machine, 6, np.random.default_rng(2), end_pause=(1.5, 2.5))
    motion, truth = planned_truth(machine, plan)
    score = score_analysis(analyze(tip_series(motion)).table, truth)
    assert score.missed == 0 and score.extra == 0
    # a smooth stop is below the speed of the bouncing for ~0.5 s before the true bound
    assert np.median(np.abs(score.end_errors)) < 0.5 and np.abs(score.end_errors).max() < 1.0
    assert np.abs(score.start_errors).max() < 1.0


def test_a_dig_pulling_towards_the_machine_is_other():
    machine, motion, truth = truth_session("bobcat_225", 4)
    backwards = _with(motion, np.arange(len(motion))[::-1])
    backwards = replace(backwards, frame=np.arange(len(motion)), time=motion.time)
    a = analyze(tip_series(backwards))
    assert np.all(a.table["class"] == "other")


def test_analyze_command_end_to_end(tmp_path):
    machine, motion, truth = truth_session("hitachi_ex3500", 3)
    path = tmp_path / "motion.csv"
    save_motion(motion, machine, path)
    assert cli.main(["analyze", "hitachi_ex3500", str(path), "--out", str(tmp_path / "out")]) == 0
    table = load_cycle_table(tmp_path / "out" / "cycles.csv")
    assert list(table)[:6] == list(FIRST)
    assert len(table["cycle"]) == len(truth["class"])
    assert list(table["class"]) == list(truth["class"])
    page = (tmp_path / "out" / "report.html").read_text()
    assert page.count("data:image/png;base64,") >= 4 and "http" not in page.replace("https://", "")
    templates = tomllib.loads((tmp_path / "out" / "templates.toml").read_text())
    chain = PlanarChain.from_machine(machine)
    for item in templates["templates"]:
        joints = np.zeros((len(item["s"]), machine.n_joints))
        for name, values in item["joints"].items():
            joints[:, machine.joint_names.index(name)] = np.radians(values)
        tip, angle = chain.forward(joints)
        expected = np.column_stack([item["start"]["reach"] + np.array(item["dx"]),
                                    item["start"]["height"] + np.array(item["dz"]) - chain.house_height])
        np.testing.assert_allclose(tip, expected, atol=1e-3)
        np.testing.assert_allclose(np.degrees(angle), item["angle_deg"], atol=1e-2)
    # --cycles keeps only the digs inside the given cycles
    given = tmp_path / "given.csv"
    save_cycle_table({"start_frame": table["start_frame"][1:3].astype(int), "end_frame": table["end_frame"][1:3].astype(int)},
                     given)
    assert cli.main(["analyze", "hitachi_ex3500", str(path), "--out", str(tmp_path / "two"), "--cycles", str(given)]) == 0
    assert len(load_cycle_table(tmp_path / "two" / "cycles.csv")["cycle"]) == 2


def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    machine, motion, _ = truth_session("hitachi_ex3500", 3)
    bad = tmp_path / "bad.csv"
    bad.write_text("frame,time,swing\n0,0,0\n")
    assert cli.main(["analyze", "hitachi_ex3500", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "header lacks" in err
    short = tmp_path / "short.csv"
    save_motion(_with(motion, np.arange(10)), machine, short)
    assert cli.main(["analyze", "hitachi_ex3500", str(short), "--out", str(tmp_path / "o")]) == 2
    assert "at least 30" in capsys.readouterr().err
    good = tmp_path / "motion.csv"
    save_motion(_with(motion, np.arange(2000)), machine, good)
    (tmp_path / "file").write_text("x")
    assert cli.main(["analyze", "hitachi_ex3500", str(good), "--out", str(tmp_path / "file")]) == 2
    assert "--out takes a folder" in capsys.readouterr().err
    far = tmp_path / "far.csv"
    far.write_text("start_frame,end_frame\n100000,100100\n")
    assert cli.main(["analyze", "hitachi_ex3500", str(good), "--out", str(tmp_path / "o"), "--cycles", str(far)]) == 2
    assert "outside the motion's frames" in capsys.readouterr().err
    with pytest.raises(InputError, match="bucket tip is missing"):
        points = motion.points.copy()
        points[: int(0.6 * len(motion))] = np.nan
        tip_series(replace(motion, points=points))
    with pytest.raises(InputError, match="time does not increase"):
        tip_series(replace(motion, time=motion.time[::-1].copy()))


def test_a_machine_that_walks_between_cycles():
    machine, motion, truth = truth_session("hitachi_ex3500", 8)
    # after the third dig the machine tracks 4 m forward and 2 m left within 10 s
    t0 = truth["dig_end_time"][2] + 6.0
    ramp = np.clip((motion.time - t0) / 10.0, 0.0, 1.0)
    shift = np.column_stack([4.0 * ramp, 2.0 * ramp, np.zeros_like(ramp)])
    walked = replace(motion, points=motion.points + shift[:, None, :],
                     extra={"base_x": shift[:, 0], "base_y": shift[:, 1]})
    a = analyze(tip_series(walked))
    score = score_analysis(a.table, truth)
    assert score.missed == 0 and score.extra == 0 and score.class_correct == score.true
    np.testing.assert_allclose(a.table["start_reach_m"], analysed("hitachi_ex3500", 8)[0].table["start_reach_m"],
                               atol=0.2)


def test_a_machine_at_rest_has_no_cycle(tmp_path, capsys):
    machine, motion, _ = truth_session("hitachi_ex3500", 3)
    path = tmp_path / "idle.csv"
    save_motion(_with(motion, np.arange(50)), machine, path)  # the hold at the start only
    assert cli.main(["analyze", "hitachi_ex3500", str(path), "--out", str(tmp_path / "out")]) == 0
    assert "no dig cycle found" in capsys.readouterr().out
    table = load_cycle_table(tmp_path / "out" / "cycles.csv")
    assert list(table)[:6] == list(FIRST) and len(table["cycle"]) == 0
    assert tomllib.loads((tmp_path / "out" / "templates.toml").read_text())["templates"] == []


@pytest.mark.parametrize("seed", [4, 13, 22])
def test_random_diggers_and_backhoe_digs(seed):
    """Machines nobody designed: a random boom-arm-bucket linkage digging like a shovel is
    segmented and classed by the rules; its backhoe digs (dragged towards the machine) and
    the Bobcat's are found with their bounds and reported `other`."""
    digger = random_digger(np.random.default_rng(seed))
    starts, ends = [], []
    for machine, classes in ((digger, CLASSES), (digger, (BACKHOE,)), (load_machine("bobcat_225"), (BACKHOE,))):
        motion, truth = planned_truth(machine, plan_session(machine, 6, np.random.default_rng(seed), classes=classes))
        a = analyze(tip_series(motion))
        score = score_analysis(a.table, truth)
        assert score.missed == 0 and score.extra == 0, machine.name
        assert score.class_correct == score.true, (machine.name, list(a.table["class"]), list(truth["class"]))
        if classes == (BACKHOE,):
            assert np.all(a.table["class"] == "other") and np.all(a.table["dig_advance_m"] < 0)
        starts.append(score.start_errors)
        ends.append(score.end_errors)
    # the bounds on the dig's bounds: median 0.5 s, none beyond 1.5 s
    for errors in (np.abs(np.concatenate(starts)), np.abs(np.concatenate(ends))):
        assert np.median(errors) < 0.5 and errors.max() < 1.5


def test_redirection_window_left_out_of_scales_and_template():
    # five digs of one class, stretched, one lifted for a while (a temporary redirection):
    # with its window left out, every scale is the true one within 0.5 % (the lift still
    # lengthens its arc) and the template is the class's shape
    rng = np.random.default_rng(7)
    s = np.linspace(0, 1, 64)
    shape = np.column_stack([4 * s - 1.5 * s**3, 3 * s**2 + 0.5 * s])
    scale = np.column_stack([rng.uniform(0.85, 1.15, 5), rng.uniform(0.85, 1.15, 5)])
    paths = np.zeros((5, 64, 3))
    paths[:, :, :2] = shape[None] * scale[:, None, :]
    inside = np.abs(s - 0.5) < 0.15
    paths[1, inside, 1] += 0.4 * np.sin(np.pi * (s[inside] - 0.35) / 0.3)
    window = np.zeros((5, 64))
    window[1, inside] = 1.0
    even = paths.copy()  # the paths as the analysis takes them: at even arc length
    for k in range(5):
        u = np.concatenate([[0], np.cumsum(np.hypot(*np.diff(paths[k, :, :2], axis=0).T))])
        u /= u[-1]
        even[k, :, 0], even[k, :, 1] = np.interp(s, u, paths[k, :, 0]), np.interp(s, u, paths[k, :, 1])
        window[k] = np.interp(s, u, window[k])
    labels = np.array(["Type 1"] * 5, dtype=object)
    templates, fitted = build_templates(DigPaths(s, even), labels, np.zeros((5, 3)), None, window)
    expected = scale / np.exp(np.log(scale).mean(axis=0))
    np.testing.assert_allclose(fitted, expected, rtol=0.005)
    size = np.exp(np.log(scale).mean(axis=0))
    sized = shape * size
    u = np.concatenate([[0], np.cumsum(np.hypot(*np.diff(sized, axis=0).T))])
    sized = np.column_stack([np.interp(s, u / u[-1], sized[:, d]) for d in range(2)])
    np.testing.assert_allclose(templates["Type 1"].path[:, :2], sized, atol=0.005 * 3.5)



@pytest.mark.parametrize("seed", [5, 17])
def test_random_digger_on_the_fitted_motion(seed):
    """A random digger filmed by 2-3 random cameras (0.5 px of pixel noise, true cameras),
    its motion fitted per frame as `mocap fit` does: every cycle is found, the dig bounds
    within the issue's (median 0.5 s, none beyond 1.5 s) and every class by the rules."""
    from mocap.reconstruct.motion import reconstruct_motion
    from mocap.synthetic.machines import SceneOptions, random_cameras

    rng = np.random.default_rng(seed)
    machine = random_digger(rng)
    plan = plan_session(machine, 4, rng)
    motion, truth = planned_truth(machine, plan)
    world = machine.markers(plan.joints(motion.time), plan.world_from_base(motion.time))  # (F, M, 3)
    cameras = random_cameras(world, SceneOptions(cameras=(2, 3)), rng)
    pixels = np.stack([c.project(world) for c in cameras]) + rng.normal(0.0, 0.5, (len(cameras), *world.shape[:2], 2))
    fitted = reconstruct_motion(machine, list(cameras), motion.frame, motion.time, pixels).motion
    tip = fitted.point("bucket_tip") - motion.point("bucket_tip")
    # the fit puts the tip within millimetres to centimetres of the truth (0.5 px at tens of metres)
    assert np.sqrt(np.nanmean(np.sum(tip**2, axis=1))) < 0.003 * np.ptp(motion.point("bucket_tip")[:, 0])
    a = analyze(tip_series(fitted))
    score = score_analysis(a.table, truth)
    assert score.missed == 0 and score.extra == 0
    for errors in (np.abs(score.start_errors), np.abs(score.end_errors)):
        assert np.median(errors) < 0.5 and errors.max() < 1.5
    assert score.class_correct == score.true, (list(a.table["class"]), list(truth["class"]))


def test_a_backhoe_dig_lowered_early_is_found_from_its_start():
    # a random digger's backhoe dig (dig 9 of this plan) whose operator lowers the bucket
    # for a while about 3 s into the drag: the tip's displacement 3 s after the start
    # points down as a lowering's does, yet the dig starts where the drag does
    machine = random_digger(np.random.default_rng(10))
    plan = plan_session(machine, 12, np.random.default_rng(1010), classes=(BACKHOE,))
    event = [s.redirection for s in plan.segments if s.dig is not None][8]
    assert event is not None and event.dz < 0 and not event.kept
    motion, truth = planned_truth(machine, plan)
    score = score_analysis(analyze(tip_series(motion)).table, truth)
    assert score.missed == 0 and score.extra == 0
    assert np.abs(score.start_errors).max() < 1.5


def test_the_score_line_says_when_scales_cannot_be_scored():
    from mocap.analysis.score import AnalysisScore, format_analysis_score

    def score(scale_errors):
        return AnalysisScore(true=2, found=2, missed=0, extra=0, start_errors=np.array([0.1, 0.2]),
                             end_errors=np.array([0.1, 0.3]), class_correct=2, redirect_tp=1, redirect_fp=0,
                             redirect_fn=0, redirect_kind_correct=1, scale_errors=np.asarray(scale_errors, float))

    assert "scale error not scored (fewer than two digs of any one class)" in format_analysis_score(score([]))
    assert "scale error median 3.0%" in format_analysis_score(score([0.02, -0.04]))
    assert "nan" not in format_analysis_score(score([]))


def _dig_series(angle_deg: np.ndarray, height: np.ndarray, reach: np.ndarray, rng: np.random.Generator):
    """A TipSeries of one dig (30 fps) with smooth (1-3 Hz) reactive noise of 1 deg and 5 cm
    (0.3 % of a 15 m reach, as the synthetic sessions have)."""
    from mocap.analysis.series import TipSeries
    n = len(angle_deg)
    t = np.arange(n) / 30.0
    smooth = lambda sd: sd * np.sin(2 * np.pi * rng.uniform(1, 3, 4)[:, None] * t + rng.uniform(0, 6, 4)[:, None]).sum(0) / 1.4  # noqa: E731
    angle = np.radians(angle_deg + smooth(1.0))
    z, r = height + smooth(0.05), reach + smooth(0.05)
    zero = np.zeros(n)
    return TipSeries(np.arange(n), t, r, z, zero, angle, zero + 1.0, zero, zero.astype(bool), zero.astype(bool), r, z, angle)


def test_a_turn_of_the_bucket_within_a_dig_is_a_redirection_and_a_late_curl_is_not():
    from mocap.analysis.shape import deviations, event_shape
    from mocap.synthetic.paths import min_jerk
    tau = np.linspace(0.0, 1.0, 225)  # a 7.5 s dig
    u = min_jerk(tau)
    # a Type 2 like dig: the tip pushes along the floor and bends up; the bucket curls late
    # and fast (45 deg as u^4), which a cubic in arc length does not follow
    curl = 45.0 * u**4
    height = 0.5 + 3.5 * np.clip((u - 0.3) / 0.7, 0, 1) ** 1.5
    reach = 10.0 + 4.0 * u
    # a temporary turn and lift (a kept step is partly taken up by the smooth profile: the
    # benchmark's misses are such)
    event = event_shape(tau, np.array([0.5]), np.array([0.1]), np.array([False]))[0]
    ends = np.array([0]), np.array([224])
    for seed in range(8):
        rng = np.random.default_rng(seed)
        none = deviations(_dig_series(curl, height, reach, rng), *ends, np.ones((1, 2)))
        found = deviations(_dig_series(curl - 10.0 * event, height + 0.3 * event, reach, rng), *ends, np.ones((1, 2)))
        assert none.redirection[0] == "none", seed
        assert found.redirection[0] != "none", seed
        # the grid's centres 0.025 of the dig apart, its half-widths 0.04 apart
        assert abs(found.redirection_centre[0] - 0.5) <= 0.1
        assert found.redirection[0] == "temporary" and -13.0 < np.degrees(found.redirection_angle[0]) < -7.0
        assert found.redirection_lift[0] > 0.1


def test_the_pruned_dtw_matrix_is_the_unpruned_one():
    """dtw_matrix prunes by each pair's Euclidean bound and takes the pairs the pruning loses
    again: the same distances as dtaidistance's unpruned matrix."""
    from dtaidistance import dtw_ndim

    from mocap.analysis.similarity import dtw_matrix

    rng = np.random.default_rng(2)
    s = np.linspace(0, 1, 64)
    path = np.stack([np.column_stack([s * (1 + 0.1 * rng.normal()), s**2 * (1 + 0.1 * rng.normal()),
                                      0.3 * s + 0.05 * rng.normal(size=64)]) for _ in range(25)])
    path[3] = path[2]  # identical digs: distance 0
    path[8] = path[7] + [0.0, 0.0, 0.01]  # a pure offset: the diagonal warping is the best, its DTW the Euclidean bound
    d = dtw_matrix(path)
    length = np.median(np.abs(path[:, -1, :2]).sum(axis=1))
    series = [np.ascontiguousarray(p / np.array([length, length, 1.0])) for p in path]
    full = np.asarray(dtw_ndim.distance_matrix_fast(series), dtype=float)
    i, j = np.triu_indices(len(path), 1)
    np.testing.assert_array_equal(d[i, j], full[i, j])
    np.testing.assert_array_equal(d, d.T)
    assert d[2, 3] == 0.0


def test_report_summary_matches_the_table_and_says_when_data_is_too_little():
    from mocap.analysis.report import render_report, summary_rows

    machine, motion, truth = truth_session("hitachi_ex3500", 3)
    a = analyze(tip_series(motion))
    times = a.table["cycle_time_s"][np.isfinite(a.table["cycle_time_s"])]
    assert len(times) == len(a) - 1  # the last cycle has no next dig
    rows = {row[0]: row for row in summary_rows(a)}
    assert rows["cycle time (s)"][1] == f"{np.median(times):.1f}" and rows["cycle time (s)"][4] == len(times)
    assert rows["dig (s)"][3] == f"{a.table['dig_s'].min():.1f}–{a.table['dig_s'].max():.1f}"
    page = render_report(a, "t")
    assert page.index("<h2>Summary") < page.index("<img")
    assert "needs two" not in page and page.count("data:image/png;base64,") == 6
    one = render_report(a.take(np.arange(len(a)) == 0), "t")
    assert "One cycle: similarity needs two." in one and "One cycle: an adjustment needs two." in one
    assert "need at least three" in one
    # the session, its plan, the class figure and the one cycle's time (its next dig is in the motion)
    assert one.count("data:image/png;base64,") == 4
