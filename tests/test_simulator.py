"""The simulated pen: API contract, determinism, chunk invariance, ranges, and physics sanity."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tactile.device.protocol import PEN_CHANNELS, PEN_RATE_HZ
from tactile.device.sim import TEXTURES, PenSimulator, Session, simulate
from tactile.errors import ConfigError

CONTACT = [t for t in TEXTURES if t != "non_contact"]


def test_textures_are_the_pen_papers() -> None:
    assert TEXTURES == (
        "desk",
        "cardboard",
        "nonwoven_cloth",
        "paper",
        "plastic_folder",
        "mouse_pad",
        "non_contact",
    )


@pytest.mark.parametrize("texture", TEXTURES)
def test_shape_dtype_and_info(texture: str) -> None:
    sim = PenSimulator(texture, seed=1)
    x = sim.read(250)
    assert x.shape == (250, len(PEN_CHANNELS)) and x.dtype == np.int16
    assert sim.n_read == 250
    assert sim.info.sample_rate_hz == PEN_RATE_HZ
    assert sim.info.channel_names[0] == "pressure_0"
    assert np.array_equal(x[:, 0], x[:, 1])  # one tip sensor, sent twice
    assert sim.read(0).shape == (0, 8)
    assert simulate(texture, 1.234, seed=1).shape == (123, 8)


def test_same_seed_same_stream_different_seed_differs() -> None:
    a = simulate("paper", 5.0, seed=3)
    assert np.array_equal(a, simulate("paper", 5.0, seed=3))
    assert not np.array_equal(a, simulate("paper", 5.0, seed=4))
    assert not np.array_equal(a, simulate("desk", 5.0, seed=3))


def test_reset_replays_the_stream() -> None:
    sim = PenSimulator("mouse_pad", seed=9)
    first = sim.read(300)
    sim.read(77)
    sim.reset()
    assert sim.n_read == 0
    assert np.array_equal(sim.read(300), first)


@pytest.mark.parametrize("texture", ["nonwoven_cloth", "plastic_folder", "non_contact"])
def test_chunk_invariance(texture: str) -> None:
    whole = PenSimulator(texture, seed=5).read(1000)
    rng = np.random.default_rng(0)
    for _ in range(4):
        sim = PenSimulator(texture, seed=5)
        parts, total = [], 0
        while total < 1000:
            n = int(min(rng.choice([0, 1, 2, 7, 31, 128, 129, 300]), 1000 - total))
            parts.append(sim.read(n))
            total += n
        assert np.array_equal(np.concatenate(parts), whole)


def test_explicit_session_is_used() -> None:
    ses = Session(force=2.0)
    sim = PenSimulator("desk", seed=2, session=ses)
    assert sim.session is ses
    assert PenSimulator("desk", seed=2).session == PenSimulator("desk", seed=2).session


def test_the_default_session_is_one_person_of_the_random_ranges() -> None:
    """Session()'s defaults (what `Session(force=2.0)` starts from, simulator.md's example)
    rocked the pen the other way from every random person and gripped it twice as stiffly as
    any; each field now lies within what Session.random draws (over 2,000 draws)."""
    rng = np.random.default_rng(0)
    drawn = [dataclasses.asdict(Session.random(rng)) for _ in range(2000)]
    for name, value in dataclasses.asdict(Session()).items():
        values = [d[name] for d in drawn]
        assert min(values) <= value <= max(values), (name, value, min(values), max(values))


def test_unknown_texture_and_bad_settings_raise_config_error() -> None:
    with pytest.raises(ConfigError, match="velvet.*desk.*non_contact"):
        PenSimulator("velvet")
    with pytest.raises(ConfigError):
        simulate("velvet", 1.0)
    with pytest.raises(ConfigError):
        PenSimulator("desk", rate_hz=0.0)
    with pytest.raises(ConfigError):
        PenSimulator("desk").read(-1)
    with pytest.raises(ConfigError):
        Session(speed=-0.1)


@pytest.mark.parametrize("texture", TEXTURES)
def test_ranges_and_gravity(texture: str) -> None:
    x = simulate(texture, 20.0, seed=11).astype(np.float64)
    assert x[:, 0].min() >= 0 and x[:, 0].max() <= 4095
    accel_g = x[:, 2:5] * PEN_CHANNELS[2].scale
    norm = np.linalg.norm(accel_g, axis=1)
    assert 0.85 < np.median(norm) < 1.2  # gravity dominates (plus stroke and vibration)
    gyro = x[:, 5:8] * PEN_CHANNELS[5].scale
    assert 0.5 < np.sqrt((gyro**2).sum(axis=1).mean()) < 200.0  # deg/s: the hand moves


def test_saturation_clips_instead_of_wrapping() -> None:
    heavy = PenSimulator("desk", seed=1, session=Session(force=80.0)).read(1000)
    assert heavy[:, 0].max() == 4095
    # Tremor peaking at ~2-3x the +/-250 deg/s range: the rails are hit, and a sample on one
    # rail is never next to one on the other (a wrap-around would put +32767 next to -32768).
    shaky = PenSimulator("non_contact", seed=1, session=Session(tremor_dps=120.0)).read(2000)
    gyro = shaky[:, 5:8].astype(np.int64)
    assert gyro.max() == 32767 and gyro.min() == -32768
    a, b = gyro[:-1], gyro[1:]
    assert not np.any((a >= 30000) & (b <= -30000) | (a <= -30000) & (b >= 30000))


def test_non_contact_has_no_pressure_and_contact_presses() -> None:
    for seed in range(4):
        air = simulate("non_contact", 10.0, seed=seed)
        assert air[:, 0].max() <= 8  # offset and noise of an unloaded sensor only
        for texture in CONTACT:
            pressed = simulate(texture, 10.0, seed=seed)
            assert np.median(pressed[:, 0]) > 30  # > 0.3 N


def _reversal_rate(gyro: np.ndarray, fs: float = PEN_RATE_HZ) -> float:
    """Sign changes per second of the 3 Hz low-passed gyro on its principal axis."""
    spec = np.fft.rfft(gyro - gyro.mean(axis=0), axis=0)
    spec[np.fft.rfftfreq(len(gyro), 1 / fs) > 3.0] = 0
    slow = np.fft.irfft(spec, len(gyro), axis=0)
    w = slow @ np.linalg.svd(slow, full_matrices=False)[2][0]
    sign = np.sign(w[np.abs(w) > 0.1 * w.std()])
    return float((np.diff(sign) != 0).sum() * fs / len(gyro))


@pytest.mark.parametrize("texture", ["paper", "non_contact"])
def test_strokes_reverse_at_a_plausible_rate(texture: str) -> None:
    for seed in range(3):
        x = simulate(texture, 30.0, seed=seed).astype(np.float64)
        rate = _reversal_rate(x[:, 5:8])
        assert 0.3 < rate < 5.0, (seed, rate)  # back-and-forth strokes: ~0.5-3 reversals/s


def _window_stats(x: np.ndarray, window: int = 200) -> np.ndarray:
    """Per window: log mean pressure, log relative pressure vibration (first differences),
    log accel and gyro high-band energy (first differences). (n_windows, 4)"""
    x = x.astype(np.float64)
    rows = []
    for i in range(0, len(x) - window + 1, window):
        w = x[i : i + window]
        p = w[:, 0] * PEN_CHANNELS[0].scale + 0.05
        rows.append(
            [
                np.log(p.mean()),
                np.log(np.diff(p).std() / p.mean() + 1e-4),
                np.log(np.diff(w[:, 2:5], axis=0).std() + 1.0),
                np.log(np.diff(w[:, 5:8], axis=0).std() + 1.0),
            ]
        )
    return np.array(rows)


def test_textures_distinguishable_by_simple_statistics() -> None:
    """Nearest centroid on 4 window statistics (2 s windows), trained on 8 sessions per texture
    and tested on 8 others, reaches >= 0.55 over the 7 textures (chance 0.14; the current
    physics gives ~0.65): texture shows across sessions. Mean pressure alone stays < 0.4,
    because the push is a property of the person, not of the surface."""

    def dataset(seeds: range) -> tuple[np.ndarray, np.ndarray]:
        feats, labels = [], []
        for k, texture in enumerate(TEXTURES):
            for seed in seeds:
                f = _window_stats(simulate(texture, 20.0, seed=seed))
                feats.append(f)
                labels += [k] * len(f)
        return np.concatenate(feats), np.array(labels)

    train_x, train_y = dataset(range(0, 8))
    test_x, test_y = dataset(range(100, 108))
    mu, sd = train_x.mean(axis=0), train_x.std(axis=0)
    train_x, test_x = (train_x - mu) / sd, (test_x - mu) / sd

    def accuracy(cols: list[int]) -> float:
        centroids = np.array([train_x[train_y == k][:, cols].mean(axis=0) for k in range(7)])
        dist = ((test_x[:, None, cols] - centroids[None]) ** 2).sum(axis=-1)
        return float((dist.argmin(axis=1) == test_y).mean())

    everything, pressure_level = accuracy([0, 1, 2, 3]), accuracy([0])
    assert everything >= 0.55, everything  # chance is 0.14
    assert pressure_level < 0.4, (pressure_level, everything)


def test_vibration_frequency_scales_with_speed() -> None:
    """Same surface and person, faster strokes: texture vibration moves up in frequency, so
    the pressure ripple's first differences grow relative to the ripple itself."""

    def ripple_ratio(speed: float) -> float:
        ses = dataclasses.replace(Session(), speed=speed, speed_jitter=0.0, lift_prob=0.0)
        p = PenSimulator("cardboard", seed=4, session=ses).read(3000)[:, 0].astype(np.float64)
        spec = np.abs(np.fft.rfft(p - p.mean())) ** 2
        f = np.fft.rfftfreq(len(p), 1 / PEN_RATE_HZ)
        return float(spec[(f > 2) & (f < 10)].sum() / spec[f > 2].sum())

    assert ripple_ratio(0.03) > ripple_ratio(0.15)


def test_a_replug_continues_the_stream_and_its_fault_schedule(monkeypatch) -> None:
    """sim:// with a stall at 1 s and an unplug at 2 s, read through a replug: one stall (it
    was repeated after every replug), the random faults go on rather than start over, and the
    pen comes back at 2 s + D with its counter from 0."""
    import serial

    import tactile.device  # noqa: F401  (registers sim://)
    from tactile.device.link import PortAbsent, open_port, read_some
    from tactile.device.protocol import Gap, Samples, StreamDecoder
    from tactile.device.sim import LinkConfig, PenLink, protocol_sim

    protocol_sim.forget_unplugs()
    monkeypatch.setattr(protocol_sim, "TRACE", True)
    url = "sim://?texture=paper&seed=3&speed=max&seconds=4&stall=1:0.3&unplug=2:0.05&drop=0.05"
    dec, events, opened = StreamDecoder(), [], 0
    link = None
    try:
        while True:
            if link is None:
                try:
                    link = open_port(url, 115200)
                    opened += 1
                except PortAbsent:  # the cable is out: try again, as tactile-run does
                    continue
            data, lost = read_some(link)
            events += dec.feed(data)
            if lost is not None:
                assert isinstance(lost, serial.SerialException)
                link.close()
                link = None
                dec.reconnected()
            elif not data and protocol_sim.last_link(url).finished:
                break
        pen = protocol_sim.last_link(url)
    finally:
        if link is not None:
            link.close()
        protocol_sim.forget_unplugs()
    assert opened == 2
    inj = pen.injected
    assert inj.stalls == 1 and inj.stalled_samples == 30 and inj.unplugs == 1
    assert inj.unplugged_samples == 5  # 0.05 s at 100 Hz: the pen is back at sample 205
    gaps = [(ev.missing, ev.reason) for ev in events if isinstance(ev, Gap)]
    assert gaps.count((30, "drop")) == 1 and gaps.count((0, "restart")) == 1, gaps
    got = sum(len(ev.raw) for ev in events if isinstance(ev, Samples))
    assert got == 400 - 30 - 5 - inj.dropped_samples == sum(pen.delivered)
    # the drops after the replug are not those of the stream's start over again
    fresh = PenLink(LinkConfig.from_query("texture=paper&seed=3&seconds=4&drop=0.05"),
                    trace=True)
    fresh.produce(400)
    lost_fresh = [i for i, v in enumerate(fresh.delivered) if not v]
    lost_after = [i - 205 for i, v in enumerate(pen.delivered) if not v and i >= 205]
    assert lost_after and lost_after != lost_fresh[: len(lost_after)]


def test_the_samples_after_a_stall_come_after_its_silence():
    """One produce() call that crossed a stall also made the frames after it, so a reader got
    the first frame after the silence before the silence (its gap event before the stall's).
    The call now ends where the silence begins; the next one goes on after the lost samples."""
    from tactile.device.protocol import StreamDecoder
    from tactile.device.sim import LinkConfig, PenLink

    link = PenLink(LinkConfig(texture="paper", seed=3, stall=(1.0, 0.5)))
    dec = StreamDecoder()
    before = [e for e in dec.feed(link.produce(1000)) if type(e).__name__ == "Samples"]
    assert before[-1].seq + len(before[-1].raw) == 100 and link.injected.stalls == 1
    after = [e for e in dec.feed(link.produce(100)) if type(e).__name__ in ("Samples", "Gap")]
    assert (type(after[0]).__name__, after[0].seq, after[0].missing) == ("Gap", 150, 50)
    assert after[1].seq == 150
