"""The label stream's post-processor, its metrics and its calibration, against values worked
out by hand on short scripted probability sequences (written here, not computed by the code
under test)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import REPO

from tactile.errors import ConfigError, ModelContractError
from tactile.postprocess.calibration import calibrate, default_grid, refusal
from tactile.postprocess.metrics import (
    WindowStream,
    compare,
    figures,
    raw_track,
    smoothed_track,
)
from tactile.postprocess.smoothing import (
    UNCERTAIN,
    PostProcessor,
    SmoothingSettings,
    check_classes,
    figures_from_metadata,
    make_settings,
    override,
    parse_smooth_option,
    settings_from_metadata,
    settings_to_metadata,
)
from tactile.runtime.stream import Label

ABC = ("a", "b", "c")
AB = ("a", "b")


def run(post: PostProcessor, rows: list, hop: float = 0.25) -> list:
    """Feed rows of probabilities at t = i * hop, seq = 100 + i."""
    return [post.update(np.array(p), i * hop, 100 + i) for i, p in enumerate(rows)]


# -- settings -----------------------------------------------------------------------------------


@pytest.mark.parametrize("kwargs, names", [
    ({"n": 0}, "n 0"), ({"n": 2.5}, "n 2.5"), ({"n": True}, "n True"),
    ({"n": None, "tau": 0.0}, "tau 0.0"), ({"n": None, "tau": float("inf")}, "tau inf"),
    ({"n": 3, "tau": 1.0}, "n=3, tau=1.0"), ({"tau": 0.5, "n": 1}, "n=1, tau=0.5"),
    ({"p_min": 1.5}, "p_min 1.5"), ({"p_min": -0.1}, "p_min -0.1"),
    ({"p_min": float("nan")}, "p_min nan"), ({"hold": 0}, "hold 0"), ({"hold": 2.0}, "hold 2.0"),
])
def test_bad_settings_are_one_line_config_errors(kwargs, names):
    with pytest.raises(ConfigError) as e:
        SmoothingSettings(**kwargs)
    assert names in str(e.value) and "\n" not in str(e.value)


def test_settings_strings():
    assert SmoothingSettings().describe() == "ma:1 p_min=0 hold=1"
    assert SmoothingSettings() == SmoothingSettings(n=1)
    assert SmoothingSettings(tau=0.5).smooth == "ema:0.5"
    assert make_settings("ema:0.75", 0.6, 2) == SmoothingSettings(None, 0.75, 0.6, 2)
    assert make_settings("ma:5", 0.6, 2).describe() == "ma:5 p_min=0.6 hold=2"
    for bad in ("ma", "ma:x", "median:3", "ema:", "5"):
        with pytest.raises(ConfigError, match="expected ma:N"):
            make_settings(bad)


def test_the_smooth_option_and_overrides_of_a_models_defaults():
    assert parse_smooth_option("5") == {"n": 5, "tau": None}
    assert parse_smooth_option("1.5s") == {"n": None, "tau": 1.5}
    assert parse_smooth_option("ema:0.5") == {"n": None, "tau": 0.5}
    assert parse_smooth_option(" ma:3 ") == {"n": 3, "tau": None}
    for bad, says in (("-1", "expected N"), ("x", "expected N"), ("s", "expected N"),
                      ("1.5:s", "expected N"), ("0", "n 0"), ("0s", "tau 0.0"),
                      ("infs", "tau inf"), ("ema:-1", "tau -1.0")):
        with pytest.raises(ConfigError, match=says) as e:
            parse_smooth_option(bad)
        assert "\n" not in str(e.value)
    model = SmoothingSettings(n=5, p_min=0.6, hold=2)
    assert override(model) is model and override(None) is None  # nothing given: as they are
    assert override(model, p_min=0.9) == SmoothingSettings(n=5, p_min=0.9, hold=2)
    assert override(model, smooth="1.5s", hold=1) == SmoothingSettings(None, 1.5, 0.6, 1)
    assert override(None, smooth="3") == SmoothingSettings(n=3)  # over no defaults: raw's
    assert override(None, hold=2) == SmoothingSettings(n=1, p_min=0.0, hold=2)
    with pytest.raises(ConfigError, match="p_min 2"):
        override(model, p_min=2)


# -- averaging ----------------------------------------------------------------------------------


def test_moving_average_values_and_ties():
    post = PostProcessor(SmoothingSettings(n=3), ABC)
    out = run(post, [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.5, 0.5], [0.0, 0.5, 0.5],
                     [0.0, 0.0, 1.0]])
    want = [[1.0, 0.0, 0.0],  # one window so far
            [0.5, 0.5, 0.0],  # a tie between a and b: the lower index leads
            [1 / 3, 0.5, 1 / 6],
            [0.0, 2 / 3, 1 / 3],  # the first window has left the average
            [0.0, 1 / 3, 2 / 3]]
    for o, w in zip(out, want):
        np.testing.assert_allclose(o.probs, w, atol=1e-12)
    assert [o.leader for o in out] == ["a", "a", "b", "b", "c"]
    assert [o.p for o in out] == pytest.approx([1.0, 0.5, 0.5, 2 / 3, 2 / 3])


def test_exponential_average_values():
    post = PostProcessor(SmoothingSettings(n=None, tau=1.0), AB)
    # windows at 0, 0.5 and 1.5 s: weights 1 - e^-0.5 = 0.3934693 and 1 - e^-1 = 0.6321206
    o0 = post.update([1.0, 0.0], 0.0, 0)
    o1 = post.update([0.0, 1.0], 0.5, 1)
    o2 = post.update([0.0, 1.0], 1.5, 2)
    np.testing.assert_allclose(o0.probs, [1.0, 0.0])  # seeded with the first window
    np.testing.assert_allclose(o1.probs, [0.6065307, 0.3934693], atol=1e-7)  # e^-0.5
    np.testing.assert_allclose(o2.probs, [0.2231302, 0.7768698], atol=1e-7)  # e^-1.5
    assert (o1.leader, o2.leader) == ("a", "b")


def test_argmax_ties_go_to_the_lowest_class_index():
    post = PostProcessor(SmoothingSettings(), ABC)
    out = run(post, [[0.4, 0.4, 0.2], [0.2, 0.4, 0.4], [0.25, 0.25, 0.5], [1 / 3, 1 / 3, 1 / 3]])
    assert [o.leader for o in out] == ["a", "b", "c", "a"]


# -- stable label and events ---------------------------------------------------------------------


def test_p_min_hold_uncertain_and_change_events():
    post = PostProcessor(SmoothingSettings(n=1, p_min=0.6, hold=2), ABC)
    out = run(post, [[0.7, 0.2, 0.1],  # a leads 1 window: uncertain
                     [0.7, 0.2, 0.1],  # a 2 windows, p 0.7: stable, first label: from None
                     [0.3, 0.5, 0.2],  # b leads with 0.5 < 0.6: uncertain
                     [0.8, 0.1, 0.1],  # a again, 1 window: uncertain
                     [0.8, 0.1, 0.1],  # a stable again: a -> uncertain -> a, no event
                     [0.05, 0.05, 0.9],  # c 1 window
                     [0.05, 0.05, 0.9],  # c stable: a -> c
                     [0.6, 0.3, 0.1],  # a, p exactly 0.6 = p_min but 1 window
                     [0.6, 0.3, 0.1]])  # a stable (p >= p_min): c -> a
    assert [o.label for o in out] == [UNCERTAIN, "a", UNCERTAIN, UNCERTAIN, "a", UNCERTAIN, "c",
                                      UNCERTAIN, "a"]
    assert [o.stable for o in out] == [False, True, False, False, True, False, True, False, True]
    assert [o.leader for o in out] == ["a", "a", "b", "a", "a", "c", "c", "a", "a"]
    assert [o.p for o in out] == pytest.approx([0.7, 0.7, 0.5, 0.8, 0.8, 0.9, 0.9, 0.6, 0.6])
    events = [(i, o.event) for i, o in enumerate(out) if o.event is not None]
    assert events == [
        (1, {"event": "change", "from": None, "to": "a", "t": 0.25, "seq": 101}),
        (6, {"event": "change", "from": "a", "to": "c", "t": 1.5, "seq": 106}),
        (8, {"event": "change", "from": "c", "to": "a", "t": 2.0, "seq": 108}),
    ]
    assert all(o.reset is None for o in out)


def test_reset_mid_hold_forgets_the_run_and_the_average_not_the_announced_label():
    post = PostProcessor(SmoothingSettings(n=2, hold=3), AB)
    a, b = [0.75, 0.25], [0.25, 0.75]
    before = [post.update(a, t, i) for i, t in enumerate([0.0, 0.25, 0.5])]
    assert [o.label for o in before] == [UNCERTAIN, UNCERTAIN, "a"]
    assert before[2].event == {"event": "change", "from": None, "to": "a", "t": 0.5, "seq": 2}
    # b for two windows: the average [0.5, 0.5] ties to a, then b leads 1 window
    mid = [post.update(b, t, i) for i, t in [(3, 0.75), (4, 1.0)]]
    assert [(o.leader, o.label) for o in mid] == [("a", "a"), ("b", UNCERTAIN)]
    post.reset("gap")  # mid-hold: b had led 1 of the 3 windows it needs
    after = [post.update(b, t, i) for i, t in [(5, 0.2), (6, 0.45), (7, 0.7), (8, 0.95)]]
    # time may start over after a reset; the average holds the new windows only
    np.testing.assert_allclose(after[0].probs, b)
    assert [o.reset for o in after] == ["gap", None, None, None]
    assert [o.label for o in after] == [UNCERTAIN, UNCERTAIN, "b", "b"]
    # the label announced before the reset is the change's "from"
    assert [o.event for o in after] == [
        None, None, {"event": "change", "from": "a", "to": "b", "t": 0.7, "seq": 7}, None]
    post.reset("reconnect")  # b again after a reset: uncertain until it holds, then no event
    again = [post.update(b, t, i) for i, t in [(9, 0.0), (10, 0.25), (11, 0.5)]]
    assert again[0].reset == "reconnect"
    assert [o.label for o in again] == [UNCERTAIN, UNCERTAIN, "b"]
    assert [o.event for o in again] == [None, None, None]


def test_json_fields_and_feed_from_a_runtime_label():
    post = PostProcessor(SmoothingSettings(), AB)
    lab = Label(seq=250, t_us=2_500_000, label="b", probability=0.75,
                probabilities={"a": 0.25, "b": 0.75}, latency_ms=0.1)
    assert post.feed(lab).to_dict() == {
        "smoothed": {"label": "b", "p": 0.75}, "stable": True,
        "event": {"event": "change", "from": None, "to": "b", "t": 2.5, "seq": 250}}
    post = PostProcessor(SmoothingSettings(p_min=0.8), AB)
    post.reset("restart")
    assert post.feed(lab).to_dict() == {"smoothed": {"label": UNCERTAIN, "p": 0.75},
                                        "stable": False, "event": None, "reset": "restart"}


def test_bad_windows_are_refused():
    post = PostProcessor(SmoothingSettings(n=None, tau=1.0), AB)
    with pytest.raises(ConfigError, match=r"expected \(2,\)"):
        post.update([0.2, 0.3, 0.5], 0.0, 0)
    with pytest.raises(ConfigError, match="finite"):
        post.update([np.nan, 1.0], 0.0, 0)
    post.update([0.5, 0.5], 1.0, 0)
    with pytest.raises(ConfigError, match="before the previous one"):
        post.update([0.5, 0.5], 0.5, 1)


def test_the_reserved_class_name_is_refused_in_one_line():
    assert check_classes(["a", "b"]) == ("a", "b")
    for make in (lambda: check_classes(("paper", "uncertain")),
                 lambda: PostProcessor(SmoothingSettings(), ("uncertain", "paper")),
                 lambda: WindowStream([0.0], [0], [[0.5, 0.5]], ("paper", "uncertain"))):
        with pytest.raises(ConfigError, match="'uncertain' is reserved") as e:
            make()
        assert "\n" not in str(e.value)


# -- metadata ------------------------------------------------------------------------------------


def test_metadata_strings_and_round_trip():
    s = SmoothingSettings(n=5, p_min=0.6, hold=2)
    meta = settings_to_metadata(s, {"setting": "ma:5 p_min=0.6 hold=2", "raw": {"a": 1}})
    assert meta == {"postprocess.version": "1", "postprocess.smooth": "ma:5",
                    "postprocess.p_min": "0.6", "postprocess.hold": "2",
                    "postprocess.calibration":
                        '{"raw": {"a": 1}, "setting": "ma:5 p_min=0.6 hold=2"}'}
    assert settings_from_metadata(meta) == s
    assert figures_from_metadata(meta) == {"setting": "ma:5 p_min=0.6 hold=2", "raw": {"a": 1}}
    e = SmoothingSettings(n=None, tau=0.75, p_min=0.55, hold=1)
    meta = settings_to_metadata(e)
    assert meta == {"postprocess.version": "1", "postprocess.smooth": "ema:0.75",
                    "postprocess.p_min": "0.55", "postprocess.hold": "1"}
    assert settings_from_metadata({"classes": "[]", **meta}) == e
    assert figures_from_metadata(meta) is None


def test_no_postprocess_keys_means_no_defaults():
    assert settings_from_metadata({}) is None
    assert figures_from_metadata({}) is None
    assert settings_from_metadata({"classes": '["a"]', "hop": "25"}) is None


@pytest.mark.parametrize("change, key", [
    ({"postprocess.p_min": "1.5"}, "postprocess.p_min"),
    ({"postprocess.p_min": "high"}, "postprocess.p_min: 'high' is not a number"),
    ({"postprocess.hold": "0"}, "postprocess.hold"),
    ({"postprocess.hold": "1e9"}, "postprocess.hold: '1e9' is not an integer"),
    ({"postprocess.smooth": "ma:0"}, "postprocess.smooth"),
    # past what a moving average can hold: was an OverflowError traceback in tactile-run
    ({"postprocess.smooth": "ma:99999999999999999999"}, "must be an integer from 1 to 100000"),
    ({"postprocess.hold": "100001"}, "hold 100001: must be an integer from 1 to 100000"),
    ({"postprocess.smooth": "median:3"}, "postprocess.smooth"),
    ({"postprocess.version": "2"}, "postprocess.version"),
    ({"postprocess.hold": None}, "postprocess.hold"),  # None: the key removed
    ({"postprocess.window": "3"}, "postprocess.window"),
    ({"postprocess.calibration": "[1, 2]"}, "postprocess.calibration"),
])
def test_bad_metadata_names_the_key(change, key):
    meta = settings_to_metadata(SmoothingSettings(n=3, p_min=0.5, hold=2))
    meta.update(change)
    meta = {k: v for k, v in meta.items() if v is not None}
    with pytest.raises(ModelContractError, match=key.replace(".", r"\.")) as e:
        settings_from_metadata(meta)
        figures_from_metadata(meta)
    assert "\n" not in str(e.value)


def test_metadata_in_an_onnx_file(tmp_path):
    """Written into a copy of the shipped model (its sha256 key removed, as after any edit by
    hand) and read back as the runtime reads a file; the shipped model's own defaults are the
    ones its export calibrated (models/README.md)."""
    import onnx

    from tactile.runtime.model import Model

    shipped = REPO / "models" / "pen-exp2.onnx"
    m = onnx.load(shipped)
    s = SmoothingSettings(n=None, tau=0.5, p_min=0.6, hold=3)
    kept = {p.key: p.value for p in m.metadata_props if p.key != "sha256"}
    del m.metadata_props[:]
    onnx.helper.set_model_props(m, {**kept, **settings_to_metadata(s, {"x": 0.5})})
    onnx.save(m, tmp_path / "m.onnx")
    meta = Model(tmp_path / "m.onnx").session.get_modelmeta().custom_metadata_map
    assert settings_from_metadata(meta) == s
    assert figures_from_metadata(meta) == {"x": 0.5}
    own = Model(shipped).session.get_modelmeta().custom_metadata_map
    assert settings_from_metadata(own) == SmoothingSettings(n=None, tau=1.0, p_min=0.5, hold=1)


# -- metrics -------------------------------------------------------------------------------------


def two_class(p_a: list[float]) -> np.ndarray:
    return np.array([[p, 1 - p] for p in p_a])


# 12 windows 0.25 s apart; truth a for 6 windows, then b. Raw argmax a a b a a a a b b a b b.
P12 = [0.9, 0.9, 0.3, 0.9, 0.9, 0.9, 0.55, 0.2, 0.2, 0.9, 0.2, 0.2]
T12 = [0] * 6 + [1] * 6


def test_metrics_raw_and_smoothed_on_a_scripted_stream():
    s = WindowStream(np.arange(12) * 0.25, T12, two_class(P12), AB)
    raw = raw_track(s)
    assert raw.events == [(0, 0), (2, 1), (3, 0), (7, 1), (9, 0), (10, 1)]
    fig = compare([s], SmoothingSettings(n=1, p_min=0.6, hold=2))
    # raw: right on 9 of 12 windows (wrong at 2, 6, 9). True changes: the start (a, at 0) and
    # b at window 6 (1.5 s). (0, a) is the start's true event, latency 0; the b change's is
    # (7, b), 0.25 s; (2, b), (3, a), (9, a), (10, b) are false. 3 min / 60 of stream (12
    # windows x 0.25 s): 4 false changes = 80 a minute. Latencies 0 and 0.25: median 0.125,
    # p95 0 + 0.95 x 0.25 = 0.2375.
    assert fig["raw"] == pytest.approx({
        "windows": 12, "minutes": 0.05, "accuracy": 0.75, "stable_accuracy": 0.75,
        "uncertain": 0.0, "changes": 2, "detected": 2, "missed": 0, "events": 6,
        "false_changes": 4, "false_per_min": 80.0, "latency_median_s": 0.125,
        "latency_p95_s": 0.2375})
    # smoothed (p_min 0.6, hold 2): U a U U a a U U b U U b; window 6 (a at 0.55) is below
    # p_min. Events (1, a) from None (latency 0.25 from the start) and (8, b) (latency 0.5
    # from 1.5 s); both true. Stable windows 1, 4, 5, 8, 11, all right: stable accuracy 1,
    # accuracy 5/12, uncertain 7/12. Median 0.375, p95 0.25 + 0.95 x 0.25 = 0.4875.
    assert fig["smoothed"] == pytest.approx({
        "windows": 12, "minutes": 0.05, "accuracy": 5 / 12, "stable_accuracy": 1.0,
        "uncertain": 7 / 12, "changes": 2, "detected": 2, "missed": 0, "events": 2,
        "false_changes": 0, "false_per_min": 0.0, "latency_median_s": 0.375,
        "latency_p95_s": 0.4875})
    track = smoothed_track(s, SmoothingSettings(n=1, p_min=0.6, hold=2))
    assert track.labels.tolist() == [-1, 0, -1, -1, 0, 0, -1, -1, 1, -1, -1, 1]
    assert track.events == [(1, 0), (8, 1)]


def test_metrics_missed_changes_and_a_label_that_came_early():
    # truth a a b b, raw a a a a: the start is detected at once, the change to b is missed
    missed = WindowStream([0.0, 0.25, 0.5, 0.75], [0, 0, 1, 1], two_class([0.8] * 4), AB)
    # truth a a b b a a, raw a b b b a a: (1, b) is false (the a interval's true event was
    # (0, a)); at the change to b the label already is b: detected, latency 0; (4, a) is true
    early = WindowStream(np.arange(6) * 0.25, [0, 0, 1, 1, 0, 0],
                         two_class([0.8, 0.3, 0.3, 0.3, 0.8, 0.8]), AB)
    f = figures([missed, early], [raw_track(missed), raw_track(early)])
    # windows 4 + 6; right 2 + 5; changes 2 + 3; detected 1 + 3; minutes (1 + 1.5) / 60
    assert f == pytest.approx({
        "windows": 10, "minutes": 2.5 / 60, "accuracy": 0.7, "stable_accuracy": 0.7,
        "uncertain": 0.0, "changes": 5, "detected": 4, "missed": 1, "events": 4,
        "false_changes": 1, "false_per_min": 24.0, "latency_median_s": 0.0,
        "latency_p95_s": 0.0})


def test_a_stream_must_be_consistent():
    with pytest.raises(ConfigError, match="truth"):
        WindowStream([0.0, 1.0], [0, 2], two_class([0.5, 0.5]), AB)
    with pytest.raises(ConfigError, match="non-decreasing"):
        WindowStream([1.0, 0.0], [0, 0], two_class([0.5, 0.5]), AB)
    with pytest.raises(ConfigError, match=r"probs \(2, 2\)"):
        WindowStream([0.0, 1.0], [0, 0], [[0.5, 0.5]], AB)


# -- calibration ---------------------------------------------------------------------------------


def flicker(b: float = 0.7) -> WindowStream:
    """One minute of a: 240 windows 0.25 s apart at p(a) 0.8, except every 10th from window 5
    on (5, 15, ..., 235: 24 windows), where b has ``b``."""
    p_a = [1 - b if i % 10 == 5 else 0.8 for i in range(240)]
    return WindowStream(np.arange(240) * 0.25, [0] * 240, two_class(p_a), AB)


def test_calibration_picks_the_clear_winner():
    ma1 = [SmoothingSettings(n=1, p_min=0.5, hold=h) for h in (1, 2, 3)]
    ma3 = SmoothingSettings(n=3, p_min=0.5, hold=1)
    cal = calibrate([flicker()], (*ma1, ma3))
    # hold 1 on the raw probabilities: (5, b) and (6, a) for each of the 24 flickers, 48 false
    # changes in the minute: over the limit. Hold 2 and 3 never let b lead long enough and
    # the moving average of 3 keeps a ahead ((0.8 + 0.8 + 0.3) / 3 = 0.633): no false change,
    # every stable window right; the average is stable at once (latency 0), hold 2 after
    # 0.25 s, hold 3 after 0.5 s: the average wins on latency.
    assert cal.settings == ma3
    f = cal.figures
    assert f["met_limit"] is True and f["setting"] == "ma:3 p_min=0.5 hold=1"
    assert (f["grid"], f["streams"]) == (4, 1)
    assert f["raw"]["false_per_min"] == 48.0 and f["raw"]["stable_accuracy"] == 0.9
    assert f["smoothed"]["false_changes"] == 0 and f["smoothed"]["latency_median_s"] == 0.0
    assert f["smoothed"]["uncertain"] == 0.0
    by = dict(cal.table)
    assert by[ma1[0]]["false_changes"] == 48 and by[ma1[0]]["stable_accuracy"] == 0.9
    # hold 2: window 0 and the flicker's two windows each time (1 + 48 of 240) uncertain
    assert by[ma1[1]]["uncertain"] == pytest.approx(49 / 240)
    assert by[ma1[1]]["latency_median_s"] == 0.25 and by[ma1[2]]["latency_median_s"] == 0.5


def test_calibration_ties_go_to_the_simplest_setting():
    # p_min 0.5 and 0.6 give the same labels here (a at 0.8, b at 0.7 for one window)
    high, low = (SmoothingSettings(n=1, p_min=p, hold=2) for p in (0.6, 0.5))
    assert calibrate([flicker()], (high, low)).settings == low


def test_calibration_without_a_setting_under_the_limit_takes_the_fewest_false_changes():
    raw = SmoothingSettings(n=1, p_min=0.5, hold=1)
    strict = SmoothingSettings(n=1, p_min=0.85, hold=1)
    # with b at 0.9, p_min 0.85 leaves every a window (0.8) uncertain and shows b, wrongly, from
    # window 5 on: one false change in the minute (from None to b), against raw's 48
    cal = calibrate([flicker(b=0.9)], (raw, strict), max_false_per_min=0.5)
    assert cal.settings == strict and cal.figures["met_limit"] is False
    assert cal.figures["smoothed"]["false_changes"] == 1
    assert cal.figures["smoothed"]["stable_accuracy"] == 0.0


def test_calibration_cap_on_uncertain_windows():
    hold2, hold3 = (SmoothingSettings(n=1, p_min=0.5, hold=h) for h in (2, 3))
    # both leave more than 10% uncertain (49 and 1 + 1 + 24 x 3 = 74 of 240): none qualifies,
    # so the fewest false changes (0 both), then the shorter latency: hold 2
    cal = calibrate([flicker()], (hold3, hold2), max_uncertain=0.1)
    assert cal.settings == hold2 and cal.figures["met_limit"] is False
    assert cal.figures["max_uncertain"] == 0.1
    assert dict(cal.table)[hold3]["uncertain"] == pytest.approx(74 / 240)
    with pytest.raises(ConfigError, match="max_uncertain"):
        calibrate([flicker()], (hold2,), max_uncertain=1.5)


def test_a_file_keeps_a_setting_that_meets_the_limits_though_it_labels_fewer_right_than_raw():
    """refusal(): a setting that meets the limits is a file's defaults even when its uncertain
    windows leave fewer windows right than the raw stream (on held-out validation streams
    that is the usual price of a stable stream); a setting that misses them is one only when
    it labels at least as many right as raw."""
    hold2 = SmoothingSettings(n=1, p_min=0.5, hold=2)
    met = calibrate([flicker()], (hold2,), max_uncertain=0.5)
    f = met.figures
    assert f["met_limit"] and f["smoothed"]["false_changes"] == 0
    assert f["smoothed"]["accuracy"] == round(191 / 240, 4) and f["raw"]["accuracy"] == 0.9
    assert refusal(met) is None
    missed = calibrate([flicker()], (hold2,), max_uncertain=0.1)  # 49 of 240 uncertain
    assert not missed.figures["met_limit"]
    assert refusal(missed) == (
        "no setting of the grid gets to at most 1 false change a minute with at most 10% of "
        "the windows uncertain, and the one with the fewest, ma:1 p_min=0.5 hold=2, gives "
        "fewer correct stable labels than the raw stream (79.6% against 90.0%)")
    raw = SmoothingSettings(n=1, p_min=0.5, hold=1)  # misses the limit, as right as raw
    assert refusal(calibrate([flicker()], (raw,), max_uncertain=0.5)) is None


def test_default_grid():
    grid = default_grid()
    assert len(grid) == 54 and len(set(grid)) == 54
    assert {s.smooth for s in grid} == {"ma:1", "ma:3", "ma:5", "ma:8", "ema:0.5", "ema:1.0"}
    assert {s.p_min for s in grid} == {0.5, 0.6, 0.7} and {s.hold for s in grid} == {1, 2, 3}


def test_calibration_prefers_correct_labels_to_uncertain_ones():
    # a throughout: p(a) 0.8 in even windows, 0.65 in odd ones, and b ahead (0.55) in window 100
    p_a = [0.45 if i == 100 else 0.8 if i % 2 == 0 else 0.65 for i in range(240)]
    stream = WindowStream(np.arange(240) * 0.25, [0] * 240, two_class(p_a), AB)
    cautious = SmoothingSettings(n=1, p_min=0.7, hold=1)
    loose = SmoothingSettings(n=1, p_min=0.5, hold=1)
    cal = calibrate([stream], (cautious, loose), max_false_per_min=2.0)
    by = dict(cal.table)
    # cautious: the 119 even windows other than 100 are stable and right, the rest uncertain
    assert by[cautious]["stable_accuracy"] == 1.0 and by[cautious]["false_changes"] == 0
    assert by[cautious]["accuracy"] == pytest.approx(119 / 240)
    # loose: every window stable, window 100 wrong: a -> b -> a, two false changes in the minute
    assert by[loose]["stable_accuracy"] == pytest.approx(239 / 240)
    assert by[loose]["false_changes"] == 2
    # the more accurate stable labels leave half the windows uncertain: the other one wins
    assert cal.settings == loose


# -- streams of samples, joined from pieces of takes -------------------------------------------


def test_a_run_is_cut_into_pieces_of_samples():
    from tactile.postprocess.streams import run_pieces

    values = np.arange(14, dtype=np.float32).reshape(7, 2)
    # 1.5 s at 2 Hz: 3 samples a piece; 7 samples make 3 + 3 + 1
    pieces = run_pieces(1, values, rate_hz=2.0, dwell_s=1.5)
    assert [p.label for p in pieces] == [1, 1, 1]
    assert [p.values[:, 0].tolist() for p in pieces] == [[0, 2, 4], [6, 8, 10], [12]]
    with pytest.raises(ConfigError, match="dwell"):
        run_pieces(1, values, rate_hz=2.0, dwell_s=0)


def test_a_window_straddling_two_pieces_gets_the_later_class():
    from tactile.postprocess.streams import Piece, join, window_ends, window_stream

    # a: samples 0..5, b: samples 6..11 at 10 Hz; windows of 4 every 3: samples 0..3, 3..6
    # (three of a, one of b), 6..9; the second's last sample is b's first
    s = join([Piece(0, np.zeros((6, 1))), Piece(1, np.ones((6, 1)))], AB, 10.0)
    assert s.truth.tolist() == [0] * 6 + [1] * 6 and s.values.dtype == np.float32
    assert window_ends(12, 4, 3).tolist() == [3, 6, 9]
    ws = window_stream(s, two_class([0.9, 0.7, 0.2]), 4, 3)
    assert ws.truth.tolist() == [0, 1, 1]
    assert ws.t.tolist() == pytest.approx([0.3, 0.6, 0.9])  # the last samples' times
    with pytest.raises(ConfigError, match="3 windows"):
        window_stream(s, two_class([0.9, 0.7]), 4, 3)


def test_raw_latency_of_a_two_piece_stream_counts_the_window_filling():
    """A pen's window of 50 samples every 25 at 100 Hz over 3.1 s of a then 2.9 s of b, with a
    model whose p(b) is the share of b samples in its window (a tie goes to a)."""
    from tactile.postprocess.streams import Piece, join, window_ends, window_stream

    s = join([Piece(0, np.zeros((310, 1))), Piece(1, np.ones((290, 1)))], AB, 100.0)
    # windows end at samples 49, 74, ..., 599 (23 windows); b starts at sample 310
    ends = np.arange(49, 600, 25)
    assert window_ends(600, 50, 25).tolist() == ends.tolist()
    p_b = [s.values[e - 49:e + 1, 0].mean() for e in ends]
    ws = window_stream(s, two_class([1 - p for p in p_b]), 50, 25)
    raw = figures([ws], [raw_track(ws)])
    # the first window ending on b ends at 324 (3.24 s): samples 275..324, 15 of b, says a;
    # the next (300..349, 40 of b) says b at 3.49 s: latency 0.25 s (0 for the stream start).
    # 11 windows of a truth, 12 of b, one of them wrong. Minutes: 0.49 .. 5.99 s + one hop.
    assert raw == pytest.approx({
        "windows": 23, "minutes": 5.75 / 60, "accuracy": 22 / 23, "stable_accuracy": 22 / 23,
        "uncertain": 0.0, "changes": 2, "detected": 2, "missed": 0, "events": 2,
        "false_changes": 0, "false_per_min": 0.0, "latency_median_s": 0.125,
        "latency_p95_s": 0.2375})


def test_streams_order_pieces_of_different_classes_next_to_each_other():
    from tactile.postprocess.streams import Piece, make_streams

    pieces = [Piece(k, np.full((2, 1), 10 * k + i)) for k in (0, 1, 2) for i in range(2)]
    a, b = make_streams({"u1": pieces, "u2": pieces[:2], "none": []}, ABC, 1.0, seed=3)
    assert len(a.truth) == 12 and (np.diff(a.truth[::2]) != 0).all()
    assert sorted(a.values[::2, 0].tolist()) == [0, 1, 10, 11, 20, 21]
    assert b.truth.tolist() == [0] * 4  # one class only: no other order possible
    again = make_streams({"u1": pieces}, ABC, 1.0, seed=3)[0]
    assert (again.values == a.values).all()  # a group's order ignores the other groups
