"""One settings object (issue 35): ``RunSettings`` is built and checked in one place by the
Python API, ``OnlineMapper``, the CLI and manifests, before any work starts; its fields keep
their names from the command line to the solver."""

from __future__ import annotations

import dataclasses

import pytest
from conftest import cli_invoke

from spdslam.experiments import JOB_SETTINGS
from spdslam.mapping import METHODS, OnlineMapper, OnlineSettings, RunSettings, SettingsError, run_online, run_sequence
from spdslam.mapping._settings import METHOD_FIELDS, RUN_OVERRIDES, RUN_SETTING_NAMES, Associate, PlaneSource, setting_help
from spdslam.synthetic import make_room_sequence


def test_defaults_and_one_name_per_setting():
    s = RunSettings.of("multi-spd")
    assert s.method == METHODS["multi-spd"] and s.associate is None and s.online is None
    assert (s.max_iterations, s.min_views, s.keyframes, s.support_planes) == (100, 3, "all", "priors")
    o = RunSettings.of("multi-rts", associate="auto", sigma={"inverse_box": 3}, keyframes="2",
                       support_planes="initial", robust=["cauchy:4", "shape=huber"],
                       online=None, truncation_margin=-1)
    assert o.associate is Associate.AUTO and o.support_planes is PlaneSource.INITIAL
    assert o.keyframes == 2 and dict(o.sigma) == {"inverse_box": 3.0}
    assert (o.method.robust, o.method.robust_k) == ("cauchy", 4.0)
    assert o.method.robust_by_type == (("shape", "huber", 1.0),) and o.method.margin is None
    on = RunSettings.of("multi-spd", online={"window": 12})
    assert on.online == OnlineSettings(window=12, every=10, iterations=5)
    assert RunSettings.of("multi-spd", online=True).online == OnlineSettings()
    assert on.as_dict()["online"]["window"] == 12 and on.as_dict()["support_planes"] == "priors"


@pytest.mark.parametrize("kwargs, field, words", [
    ({"method": "orb-slam"}, "method", "expected one of quadric-slam"),
    ({"associate": "ids"}, "associate", "expected one of instances, auto, got 'ids'"),
    ({"max_iterations": 0}, "max_iterations", "expected an integer ≥ 1, got 0"),
    ({"max_iterations": True}, "max_iterations", "expected an integer"),
    ({"min_views": 2.5}, "min_views", "expected an integer ≥ 1, got 2.5"),
    ({"tolerance": float("nan")}, "tolerance", "expected a finite number ≥ 0"),
    ({"keyframes": "often"}, "keyframes", "must be all, motion or a positive integer"),
    ({"support_planes": "floor"}, "support_planes", "expected one of priors, initial, optimised"),
    ({"sigma": {"inverse_boxx": 1}}, "sigma", "expected a sigma among"),
    ({"sigma": {"inverse_box": -1}}, "sigma", "finite positive value for inverse_box"),
    ({"screen": "yes"}, "screen", "expected true or false"),
    ({"parameterization": "quat"}, "parameterization", "must be one of spd, rts, full"),
    ({"truncation_margin": float("inf")}, "truncation_margin", "must be finite"),
    ({"robust": ["bogus"]}, "robust", "expected KERNEL or TYPE=KERNEL[:K]"),
    ({"robust": [3]}, "robust", "expected KERNEL or a list"),
    ({"sigma": [1]}, "sigma", "expected a mapping NAME: VALUE"),
    ({"truncation_margin": "x"}, "truncation_margin", "expected a number, got 'x'"),
    ({"robust_k": "a"}, "robust_k", "expected a number"),
    ({"support_plane": "yes"}, "support_plane", "expected true or false, got 'yes'"),
    ({"orientation": 1}, "orientation", "expected a string"),
    ({"min_views": "3"}, "min_views", "expected an integer ≥ 1, got '3'"),
    ({"online": {"window": 1}}, "online.window", "expected an integer ≥ 2, got 1"),
    ({"online": {"lag": 3}}, "online", "expected keys among window, every"),
    ({"online": True, "keyframes": 3}, "keyframes", "an online run uses every frame"),
    ({"online": True, "support_planes": "optimised"}, "support_planes", "from the priors only"),
    ({"online": True, "parameterization": "full"}, "parameterization", "SPD or RTS landmarks"),
    ({"online": True, "box_model": "semi-then-inverse"}, "box_model", "one box model"),
])
def test_a_bad_setting_is_named(kwargs, field, words):
    kwargs = dict(kwargs)
    method = kwargs.pop("method", "multi-spd")
    with pytest.raises(SettingsError) as e:
        RunSettings.of(method, **kwargs)
    assert e.value.field == field and words in str(e.value), str(e.value)
    assert str(e.value).startswith(f"{field}: ")


def test_unknown_keywords_and_settings_given_twice_are_refused():
    with pytest.raises(TypeError, match="unknown settings sigmas"):
        RunSettings.of("multi-spd", sigmas={})
    with pytest.raises(TypeError, match="settings given twice"):
        run_sequence(make_room_sequence(0, 20, 1), RunSettings.of(), max_iterations=3)


def test_settings_are_checked_before_any_work(monkeypatch):
    """A bad setting ends ``run_sequence`` before the screen, the association or anything
    else runs (support planes were checked only after association before)."""
    import spdslam.mapping._batch as run_mod

    def never(*a, **k):
        raise AssertionError("work started before the settings were checked")

    monkeypatch.setattr(run_mod, "screen_detections", never)
    monkeypatch.setattr(run_mod, "SequenceContext", never)
    seq = make_room_sequence(0, 20, 1)
    for bad in ({"support_planes": "floor"}, {"keyframes": 0}, {"sigma": {"x": 1}}):
        with pytest.raises(SettingsError):
            run_sequence(seq, "multi-spd", **bad)
    with pytest.raises(SettingsError, match="online"):
        run_sequence(seq, RunSettings.of(online=True))


def test_the_online_mapper_takes_the_same_settings():
    room = make_room_sequence(0, 30, 2)
    s = RunSettings.of("multi-spd", associate="instances", online={"window": 8, "every": 4})
    a = OnlineMapper(room.camera, room.priors, s)
    b = OnlineMapper(room.camera, room.priors, "multi-spd", associate="instances", window=8, every=4)
    assert a.settings == b.settings and (a.window, a.every) == (8, 4)
    assert OnlineMapper(room.camera, room.priors).settings.associate == "auto"
    with pytest.raises(TypeError, match="online settings given twice"):
        OnlineMapper(room.camera, room.priors, s, window=3)
    # run_online with a RunSettings: tests/test_online.py (beside the other replays' programs)


def test_the_cli_and_the_manifest_take_their_names_and_help_from_the_settings():
    names = set(RUN_SETTING_NAMES) - {"method"}
    assert names | set(METHOD_FIELDS) | {"overlay"} == set(JOB_SETTINGS)
    assert set(RUN_OVERRIDES) <= set(METHOD_FIELDS)
    for name in names:
        assert JOB_SETTINGS[name] == setting_help(name)
    import typer

    from spdslam import cli

    run = typer.main.get_command(cli.app).commands["run"]
    params = {p.name: p for p in run.params}
    for option, name in (("max_iterations", "max_iterations"), ("keyframes", "keyframes"),
                         ("class_table", "class_table"), ("window", "online.window"),
                         ("online_iterations", "online.iterations")):
        text = setting_help(name)
        assert text[1:] in params[option].help, option
    assert params["method"].default == RunSettings.method.name
    for name in set(RUN_SETTING_NAMES) - {"online", "method"}:  # every setting is an option
        assert name in params and params[name].default in (getattr(RunSettings, name, None), None), name
    online = {f.name: f.default for f in dataclasses.fields(OnlineSettings)}
    assert (params["window"].default, params["every"].default) == (online["window"], online["every"])
    assert params["max_iterations"].default == RunSettings.max_iterations


def test_a_bad_option_is_named_on_the_command_line(tmp_path):
    r = cli_invoke("run", str(tmp_path), "--online", "--every", "0", "--out", str(tmp_path / "o"))
    assert r.exit_code == 2 and "--every: expected an integer ≥ 1, got 0" in r.stderr
    assert not (tmp_path / "o").exists()
