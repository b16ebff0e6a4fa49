"""Datasets as windows: cut recordings into windows, split them without leaks, normalise.

No window spans a recorded gap (windows are cut inside :meth:`Take.segments`), no take (or
user) gives windows to two splits, and normalisation statistics come from training windows only.
"""

from __future__ import annotations

import fnmatch
import math
import re
from dataclasses import dataclass

import numpy as np

from tactile.device.recordings import Take, load_dataset
from tactile.device.recordings.reader import copies
from tactile.device.recordings.take_meta import signal_order_differs
from tactile.errors import ConfigError, RecordingError
from tactile.training.config import SELECTOR, TrainConfig, reads_signals


@dataclass
class Windows:
    """Windows of one split.

    x: (N, window, C) float32 values in the channels' units; y: (N,) class index;
    take: (N,) index of the take each window came from; start: (N,) first row in that take;
    run: (N,) id of the gap-free run (segment) the window lies in, for carried-state runs.
    """

    x: np.ndarray
    y: np.ndarray
    take: np.ndarray
    start: np.ndarray
    run: np.ndarray

    def __len__(self) -> int:
        return len(self.y)

    def subset(self, mask: np.ndarray) -> Windows:
        w = self
        return Windows(w.x[mask], w.y[mask], w.take[mask], w.start[mask], w.run[mask])


def concat(a: Windows, b: Windows) -> Windows:
    """The windows of ``a`` then ``b``; ``b``'s run ids are moved past ``a``'s."""
    run = b.run + (int(a.run.max()) + 1 if len(a) else 0)
    return Windows(*(np.concatenate([u, v]) for u, v in (
        (a.x, b.x), (a.y, b.y), (a.take, b.take), (a.start, b.start), (a.run, run))))


def classes_of(takes: list[Take]) -> tuple[str, ...]:
    return tuple(sorted({t.label for t in takes}))


def channel_index(take: Take, channels: tuple[str, ...]) -> list[int]:
    if not channels:
        return list(range(len(take.channels)))
    missing = [c for c in channels if c not in take.channels]
    if missing:
        raise ConfigError(f"channels {missing} not in the recordings' {list(take.channels)}")
    return [take.channels.index(c) for c in channels]


def pick_channels(take: Take, patterns: tuple[str, ...]) -> tuple[str, ...]:
    """The channels of ``take`` that the ``channels`` setting picks, in its order: an exact
    name, or a shell-style pattern (``f0_*``) for the channels it matches in recording order
    (empty: all of them). A name or pattern that picks nothing, or a channel picked twice, is
    a :class:`ConfigError`."""
    if not patterns:
        return tuple(take.channels)
    missing = [p for p in patterns if p not in take.channels and not any(
        ch in p for ch in "*?[")]
    if missing:  # exact names: the recordings' own error, naming all of them
        channel_index(take, tuple(missing))
    out: list[str] = []
    for p in patterns:
        if p in take.channels:  # a channel's own name first (names may hold * ? [)
            hit = [p]
        else:
            hit = [c for c in take.channels if fnmatch.fnmatchcase(c, p)]
            if not hit:
                raise ConfigError(f"channels pattern {p!r} matches none of the recordings' "
                                  f"channels: {name_list(list(take.channels))}")
        twice = [c for c in hit if c in out]
        if twice:
            raise ConfigError(f"channels picks {twice[0]!r} twice ({p!r} again)")
        out += hit
    return tuple(out)


def ordered_signals(config) -> tuple:
    """The high-rate signals a model reads in time order, as (name, channels) pairs, from its
    config (a :class:`TrainConfig` or a checkpoint's dict): a granular model's, a ``linear``
    head's or a spectral front's; an lstm with ``front='none'`` reads the sub-samples as
    plain channels, in any order (its config keeps ``[signals]`` as written), so none."""
    if not reads_signals(config):
        return ()
    signals = (config.get("signals") if isinstance(config, dict) else config.signals) or ()
    return tuple(signals.items()) if isinstance(signals, dict) else tuple(signals)


def check_model_input(takes: list[Take], channels: tuple[str, ...], units, rate_hz,
                      data: object, signals=()) -> None:
    """The takes carry what a trained model reads, as ``tactile-run`` checks a device: each
    of ``channels`` (missing: :func:`channel_index`'s error), in the model's unit (``units``,
    in ``channels``' order; None: not recorded, not checked; a take of a CSV device, which
    declares no units, is taken in the model's), at the model's rate
    (``rate_hz``; None: not checked), and no take declares a high-rate signal's sub-samples in
    another time order than the model's ``signals`` ((name, channels) pairs). Else a
    :class:`RecordingError` naming the first difference and ``data`` (the folder): a model's
    figures on windows it would misread."""
    for take in takes:
        differs = signal_order_differs(take.meta.get("signals", {}), signals)
        if differs:
            raise RecordingError(f"{take.path}: {differs}")
        index = channel_index(take, channels)
        # a CSV device's take declares no units: taken in the model's, as tactile-run takes
        # a CSV device's values
        if units is not None and not take.info.units_unknown:
            got = [take.info.channels[i].unit for i in index]
            bad = [k for k, (u, want) in enumerate(zip(got, units)) if u != want]
            if bad:
                k = bad[0]
                raise RecordingError(
                    f"{take.path}: {channels[k]} is in {got[k]!r}, the model reads it in "
                    f"{units[k]!r}" + (f" (and {len(bad) - 1} more channels)" if len(bad) > 1
                                       else ""))
    if rate_hz is not None and takes and not math.isclose(
            takes[0].info.sample_rate_hz, float(rate_hz), rel_tol=1e-3):
        raise RecordingError(f"{data}: recorded at {takes[0].info.sample_rate_hz:g} Hz, the "
                             f"model reads {float(rate_hz):g} Hz")


def cut(
    takes: list[Take],
    classes: tuple[str, ...],
    channels: tuple[str, ...],
    window: int,
    hop: int,
    rows: dict[int, tuple[int, int]] | None = None,
    shift: int = 0,
) -> Windows:
    """Windows from ``takes`` (optionally only rows [a, b) of take i: ``rows[i]``).

    ``shift`` moves every window start by that many samples (the robustness check's shifted
    windows); windows that would leave their segment are not made.
    """
    xs, ys, tk, st, rn = [], [], [], [], []
    run_id = 0
    for i, take in enumerate(takes):
        if rows is not None and i not in rows:
            continue
        lo, hi = rows[i] if rows is not None else (0, len(take.seq))
        values = take.values()[:, channel_index(take, channels)].astype(np.float32)
        y = classes.index(take.label)
        for a, b in take.segments():
            a, b = max(a, lo), min(b, hi)
            starts = np.arange(a, b - window + 1, hop) + shift
            starts = starts[(starts >= a) & (starts + window <= b)]
            if len(starts):
                idx = starts[:, None] + np.arange(window)[None, :]
                xs.append(values[idx])
                ys.append(np.full(len(starts), y))
                tk.append(np.full(len(starts), i))
                st.append(starts)
                rn.append(np.full(len(starts), run_id))
            run_id += 1
    if not xs:
        raise ConfigError(f"no window of {window} samples fits in the selected recordings")
    return Windows(
        np.concatenate(xs), np.concatenate(ys), np.concatenate(tk), np.concatenate(st),
        np.concatenate(rn),
    )


def groups_of(takes: list[Take], split: str) -> tuple[np.ndarray, list[str]]:
    """(n_takes,) group id and the groups' names: the user (when every take says so, for
    ``split='user'``) or the take itself (its file name without extension)."""
    lacking = [t for t in takes if "user" not in t.meta]
    if split == "user" and lacking and len(lacking) < len(takes):
        # per take, a user's other takes could land in training beside its test take
        raise ConfigError(f"split='user': {len(lacking)} of {len(takes)} takes have no 'user' "
                          f"field (e.g. {lacking[0].path.name}): give every take one, or use "
                          "split='take'")
    if split == "user" and not lacking:
        users = sorted({str(t.meta["user"]) for t in takes})
        return np.array([users.index(str(t.meta["user"])) for t in takes]), users
    return np.arange(len(takes)), [t.path.stem for t in takes]


def _field(take: Take, field: str):
    return take.path.stem if field == "name" else take.meta.get(field)


def select(takes: list[Take], spec: str, key: str = "test") -> set[int]:
    """Indices of the takes that ``spec`` (``FIELD:VALUE[,VALUE...]``, see
    :class:`TrainConfig`) names. A field no take has, or a spec that matches no take, is a
    :class:`ConfigError` naming ``key`` and what the takes hold."""
    m = SELECTOR.match(spec)
    if m is None:
        raise ConfigError(f"{key}={spec!r}: expected FIELD:VALUE[,VALUE...]")
    field, values = m["field"], [v.strip() for v in m["values"].split(",") if v.strip()]
    have = [_field(t, field) for t in takes]
    if all(v is None for v in have):
        fields = sorted({k for t in takes for k, v in t.meta.items()
                         if isinstance(v, (str, int)) and not isinstance(v, bool)} | {"name"})
        raise ConfigError(f"{key}={spec!r}: no take has a {field!r} field "
                          f"(fields: {', '.join(fields)})")
    chosen = {i for i, v in enumerate(have) if v is not None and any(
        _matches(v, pattern) for pattern in values)}
    if not chosen:
        seen = sorted({str(v) for v in have if v is not None})
        raise ConfigError(f"{key}={spec!r}: matches no take ({field} values: "
                          f"{name_list(seen, 8)})")
    return chosen


def _matches(value, pattern: str) -> bool:
    """A shell-style pattern on the value's text, or an inclusive range ``a-b`` of integers."""
    r = re.fullmatch(r"(-?\d+)-(-?\d+)", pattern)
    if r and not isinstance(value, bool):
        try:
            number = int(value)
        except (TypeError, ValueError):
            number = None
        if number is not None and int(r[1]) <= number <= int(r[2]):
            return True
    return fnmatch.fnmatchcase(str(value), pattern)


def name_list(names: list[str], most: int = 12) -> str:
    """``a, b, c`` or, past ``most`` names, the first ones and how many there are in all."""
    if len(names) <= most:
        return ", ".join(names)
    return ", ".join(names[: most - 2]) + f", ... ({len(names)} in all)"


@dataclass
class Split:
    train: dict[int, tuple[int, int]]
    val: dict[int, tuple[int, int]]
    test: dict[int, tuple[int, int]]
    description: str
    shared: str | None = None  # users in two parts (test/val named by take): a warning
    by_class: bool = False  # the draw went class by class (groups of one class each)


def split_takes(takes: list[Take], cfg: TrainConfig) -> Split:
    """Assign takes (or row ranges of takes) to train / validation / test, deterministically.

    ``cfg.test`` / ``cfg.val`` name their takes (:func:`select`); what they leave to chance is
    drawn from ``cfg.seed`` in whole groups (users or takes, :func:`groups_of`)."""
    rng = np.random.default_rng(cfg.seed)
    if cfg.split == "time":
        train, val, test = {}, {}, {}
        for i, t in enumerate(takes):
            n = len(t.seq)
            cut_test = int(round(n * (1 - cfg.test_fraction)))
            cut_val = int(round(cut_test * (1 - cfg.val_fraction)))
            train[i], val[i], test[i] = (0, cut_val), (cut_val, cut_test), (cut_test, n)
        return Split(train, val, test, f"time: first {1 - cfg.test_fraction:.0%} of each take "
                     f"trains (last {cfg.val_fraction:.0%} of it validates), the rest tests")
    groups, group_names = groups_of(takes, cfg.split)
    every = set(range(len(takes)))
    named_test = select(takes, cfg.test, "test") if cfg.test else None
    named_val = select(takes, cfg.val, "val") if cfg.val else None
    if named_test is not None and named_val is not None and named_test & named_val:
        both = sorted(takes[i].path.stem for i in named_test & named_val)
        raise ConfigError(f"test={cfg.test!r} and val={cfg.val!r} both take {name_list(both, 4)}")
    # the random draw, in whole groups, among the takes no selector named
    free = every - (named_test or set()) - (named_val or set())
    free_groups = np.unique(groups[sorted(free)]) if free else np.array([], int)
    labels_of = {int(g): {takes[i].label for i in free if groups[i] == g} for g in free_groups}
    by_label: dict[str, list[int]] = {}
    for g, labels in labels_of.items():
        by_label.setdefault(next(iter(labels)), []).append(g)
    by_class = len(by_label) > 1 and all(len(v) == 1 for v in labels_of.values())
    if by_class:
        # groups of one class each (takes with no user): drawn class by class, so that every
        # class with takes enough has some in validation and in test, and keeps one to train
        drawn_test, drawn_val = set(), set()
        for label in sorted(by_label):
            ids = rng.permutation(by_label[label])
            n = len(ids)
            n_test = 0 if named_test is not None else min(
                max(1, int(round(n * cfg.test_fraction))), n - 1)
            n_val = 0 if named_val is not None else max(0, min(
                max(1, int(round((n - n_test) * cfg.val_fraction))), n - n_test - 1))
            drawn_test |= set(ids[:n_test].tolist())
            drawn_val |= set(ids[n_test : n_test + n_val].tolist())
        if (named_test is None and not drawn_test) or (named_val is None and not drawn_val):
            raise ConfigError(
                f"{len(np.unique(groups))} "
                f"{'users' if len(group_names) < len(takes) else 'takes'} of one class each "
                "cannot be split into train, validation and test (a class needs 3 for one in "
                "each): record more takes, name the test/validation takes or use "
                "split='time'")
    else:
        ids = rng.permutation(free_groups)
        n_test = 0 if named_test is not None else max(
            1, int(round(len(ids) * cfg.test_fraction)))
        n_val = 0 if named_val is not None else max(
            1, int(round((len(ids) - n_test) * cfg.val_fraction)))
        if len(ids) - n_test - n_val < 1:
            raise ConfigError(
                f"{len(np.unique(groups))} {cfg.split}s cannot be split into train, validation "
                "and test: record more takes, name fewer test/validation takes or use "
                "split='time'")
        drawn_test = set(ids[:n_test].tolist())
        drawn_val = set(ids[n_test : n_test + n_val].tolist())
    test = named_test if named_test is not None else {i for i in free if groups[i] in drawn_test}
    val = named_val if named_val is not None else {i for i in free if groups[i] in drawn_val}
    train = every - test - val
    whole = {i: (0, len(t.seq)) for i, t in enumerate(takes)}

    def names(part: set[int]) -> list[str]:
        return sorted({group_names[groups[i]] for i in part})

    unit = "user" if cfg.split == "user" and all("user" in t.meta for t in takes) else "take"
    def named(spec: str) -> str:
        return f" ({spec})" if spec else ""

    description = (
        f"{cfg.split}: test {unit}s {name_list(names(test))}{named(cfg.test)}; "
        f"validation {unit}s {name_list(names(val))}{named(cfg.val)}; "
        f"train {unit}s {name_list(names(train))}")
    # a selector names takes: the other takes of its users may fall to another part
    shared = []
    for part, key, held in (("test", "test", test), ("validation", "val", val)):
        both = sorted(set(names(held)) & set(names(train)))
        if both and getattr(cfg, key):
            who = (f"{unit} {both[0]} has" if len(both) == 1
                   else f"{unit}s {name_list(both, 4)} have")
            shared.append(f"{who} takes in {part} and in training ({key}={getattr(cfg, key)!r} "
                          f"names takes, not whole {unit}s): the {part} figures include "
                          f"{unit}s seen in training")
    part_of = {**{i: "training" for i in train}, **{i: "validation" for i in val},
               **{i: "test" for i in test}}
    order = ("training", "validation", "test")
    alike: dict[int, list[int]] = {}
    for i, j in copies(takes):  # the takes of each recording, the first one's index as key
        alike.setdefault(j, [j]).append(i)
    for group in alike.values():  # a recording in two parts: the later part's figures
        where = {}
        for i in group:
            where.setdefault(part_of[i], i)
        parts = sorted(where, key=order.index)
        for b in parts[1:]:
            a = parts[0]
            shared.append(f"{takes[where[a]].path.name} and {takes[where[b]].path.name} hold "
                          f"the same recording, one in {a} and one in {b}: the {b} figures "
                          f"include a recording {'trained' if a == 'training' else 'validated'} "
                          "on")
    return Split({i: whole[i] for i in sorted(train)}, {i: whole[i] for i in sorted(val)},
                 {i: whole[i] for i in sorted(test)}, description, "; ".join(shared) or None,
                 by_class)



def split_windows(takes: list[Take], classes: tuple[str, ...], channels: tuple[str, ...],
                  cfg: TrainConfig) -> tuple[Split, dict[str, Windows]]:
    """The split ``cfg`` gives (:func:`split_takes`) and its windows, ``{"train", "val",
    "test"}``: what training fits, stops early on and reports (baselines use the same)."""
    split = split_takes(takes, cfg)
    parts = {name: cut(takes, classes, channels, cfg.window, cfg.hop, rows)
             for name, rows in (("train", split.train), ("val", split.val), ("test", split.test))}
    return split, parts

def channel_stats(w: Windows) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel mean and std (C,) over training windows; a constant channel gets std 1."""
    flat = w.x.reshape(-1, w.x.shape[-1]).astype(np.float64)
    mean, std = flat.mean(0), flat.std(0)
    std[std < 1e-8] = 1.0
    return mean.astype(np.float32), std.astype(np.float32)


def model_data(ck: dict, data, folder: str, signals) -> tuple:
    """DATA's takes as a trained model reads them, for figures on them (``tactile-eval``,
    ``tactile-export --data``, ``tactile-check --data``): (takes, rows, scope, seen). Their
    labels must be among the model's classes and they must carry what it reads
    (:func:`check_model_input`, ``signals`` the ones it reads in time order); ``rows`` is the
    run's test split when DATA holds it (:func:`find_test_split`, ``folder`` naming DATA in
    ``scope``), else None (every row); ``seen``: the takes the run trained or validated on
    among them ([] for its test split; None: not known), named at the end of ``scope``."""
    takes = load_dataset(data)
    classes = list(ck["classes"])
    unknown = sorted({t.label for t in takes} - set(classes))
    if unknown:  # a figure on some of DATA's takes would not be DATA's
        raise RecordingError(f"{data}: labels {unknown} are not among the model's {classes}")
    check_model_input(takes, tuple(ck["channels"]), ck.get("units"), ck.get("sample_rate_hz"),
                      data, signals)
    rows, scope, _ = find_test_split(takes, ck.get("test_rows"), ck.get("test_fingerprints"),
                                     folder)
    seen = [] if rows is not None else seen_takes(takes, ck.get("seen_fingerprints"))
    return takes, rows, scope + seen_note(seen), seen


def seen_takes(takes: list[Take], seen: object) -> list[str] | None:
    """The file names of ``takes`` that a run trained or validated on, by content: ``seen`` is
    its ``seen_fingerprints`` (read defensively); None when the run kept none (saved before
    they were kept, or a file exported from such a run): not known."""
    if not isinstance(seen, (list, tuple)) or not all(isinstance(v, str) for v in seen):
        return None
    known = set(seen)
    return [t.path.name for t in takes if t.fingerprint() in known]


def seen_note(names: list[str] | None) -> str:
    """What a figure on takes a run has seen is (empty when none were, or it is not known)."""
    if not names:
        return ""
    return (f"; {len(names)} of them the run trained or validated on (by content, e.g. "
            f"{names[0]}): these figures are not a test")


def find_test_split(takes: list[Take], test_rows: object, fingerprints: object,
               folder: str) -> tuple[dict[int, tuple[int, int]] | None, str, bool]:
    """Which rows of ``takes`` are a run's test split, recognised by content.

    Args:
        takes: the dataset's takes; test_rows: the run's ``{take file name: [start, end)}``;
        fingerprints: its ``{take file name: Take.fingerprint()}`` (absent in runs trained before
        they were recorded); both read defensively (anything malformed counts as absent).
        folder: the dataset's name, for the description.

    Returns:
        rows: {take index: (start, end)}, or None for every row of every take.
        scope: what the rows are, for people.
        verified: True when every test take was found with the recorded fingerprint.
    """
    names = [t.path.name for t in takes]
    rows_ok = isinstance(test_rows, dict) and test_rows and all(
        isinstance(v, (list, tuple)) and len(v) == 2 and all(isinstance(i, int) for i in v)
        for v in test_rows.values())
    if not rows_ok or not all(n in names for n in test_rows):
        return None, f"every take of {folder} ({len(takes)} takes)", False
    rows = {names.index(n): (int(r[0]), int(r[1])) for n, r in test_rows.items()}
    fps_ok = isinstance(fingerprints, dict) and all(
        isinstance(fingerprints.get(n), str) for n in test_rows)
    if not fps_ok:
        return rows, (f"the takes of {folder} named like the run's test split ({len(rows)} takes; "
                      "the run recorded no fingerprints, so their content is not verified)"), False
    differ = [n for n in test_rows
              if takes[names.index(n)].fingerprint() != fingerprints[n]]
    if differ:
        return None, (f"every take of {folder} ({len(takes)} takes; {len(differ)} named like "
                      f"the run's test takes hold other recordings, e.g. {differ[0]})"), False
    return rows, f"the run's test split in {folder} ({len(rows)} takes, matched by content)", True
