"""A take's JSON read back and checked key by key, before anything trusts it.

The file is untrusted (a take from elsewhere, edited by hand, or damaged): :func:`read_meta`
checks every key the reader uses against a small schema (required or not, type, range), then
the device header against :class:`~tactile.device.protocol.info.DeviceInfo`'s own limits, and
raises one :class:`RecordingError` line naming the file and the key, never a traceback.
"""

from __future__ import annotations

import json
import re
import unicodedata
from pathlib import Path

from tactile.device.protocol.info import DeviceInfo
from tactile.errors import RecordingError, TactileError

FORMAT = "tactile-recording"
VERSION = 2  # 2: gap lines in the CSV, channel names escaped in its header
READABLE_VERSIONS = (1, 2)


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _count(v) -> bool:
    return _is_int(v) and v >= 0


def _text(v) -> bool:
    return isinstance(v, str)


# What a take's JSON may hold: key -> (required, test, what it must be). Other keys are the
# recorder's extras (user, simulator...) and are kept as they are.
_META = {
    "format": (True, lambda v: v == FORMAT, f'"{FORMAT}"'),
    "version": (True, lambda v: _is_int(v) and v in READABLE_VERSIONS,
                " or ".join(map(str, READABLE_VERSIONS))),
    "label": (True, lambda v: _text(v) and v != "", "a non-empty string"),
    "device": (True, lambda v: isinstance(v, dict), "an object (the device header)"),
    "started_utc": (False, _text, "a string"),
    "source": (False, _text, "a string"),
    "columns": (False, lambda v: isinstance(v, list) and all(map(_text, v)),
                "a list of strings"),
    "samples": (False, _count, "an integer >= 0"),
    "first_seq": (False, lambda v: v is None or _count(v), "an integer >= 0 or null"),
    "last_seq": (False, lambda v: v is None or _count(v), "an integer >= 0 or null"),
    "gaps": (False, lambda v: isinstance(v, list), "a list"),
    "decoder": (False, lambda v: isinstance(v, dict), "an object"),
    "complete": (False, lambda v: isinstance(v, bool), "true or false"),
    "user": (False, lambda v: (_text(v) and v.strip() != "") or _is_int(v),
             "a non-empty string or an integer (who recorded it: training's split by user)"),
    "signals": (False, lambda v: isinstance(v, dict) and all(
        isinstance(k, str) and k and isinstance(c, list) and c and all(map(_text, c))
        for k, c in v.items()), "an object of signal name -> non-empty list of channel names"),
}
RESERVED_KEYS = frozenset(_META)
"""The keys a take's JSON gives the format itself: a recorder's extra keys (``tactile-record
--meta``) must be others."""

_DEVICE = {
    "sample_rate_hz": (True, _is_number, "a number"),
    "channels": (True, lambda v: isinstance(v, list) and len(v) > 0, "a non-empty list"),
    "device": (False, _text, "a string"),
    "protocol_version": (False, _is_int, "an integer"),
}
_CHANNEL = {
    "name": (True, _text, "a string"),
    "unit": (True, _text, "a string"),
    "scale": (False, _is_number, "a number"),
    "offset": (False, _is_number, "a number"),
}
_GAP = {
    "seq": (True, _count, "an integer >= 0"),
    "missing": (True, _count, "an integer >= 0"),
    "reason": (True, _text, "a string"),
}


def _shown(v) -> str:
    if isinstance(v, dict | list):
        return f"{'an object' if isinstance(v, dict) else 'a list'} of {len(v)}"
    text = repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


def _check(obj, schema: dict, where: str, path: Path, closed: bool = False) -> None:
    """Raise a :class:`RecordingError` naming ``path`` and the key if ``obj`` breaks ``schema``
    (``closed``: no other keys allowed)."""
    if not isinstance(obj, dict):
        raise RecordingError(f"{path}: {where or 'the top level'} must be an object, "
                             f"got {_shown(obj)}")
    dot = f"{where}." if where else ""
    for key, (required, ok, what) in schema.items():
        if key not in obj:
            if required:
                raise RecordingError(f"{path}: key '{dot}{key}' missing")
        elif not ok(obj[key]):
            raise RecordingError(f"{path}: key '{dot}{key}' must be {what}, got "
                                 f"{_shown(obj[key])}")
    if closed and (extra := sorted(set(obj) - set(schema))):
        raise RecordingError(f"{path}: key '{dot}{extra[0]}' unknown; allowed: "
                             f"{', '.join(schema)}")


# A label names the take's files and a class; these are refused by FAT/exFAT cards (a board's
# usual storage) or break the CSV/JSON pair: / \ : * ? " < > | , control characters.
# A lone surrogate is a byte of a command-line argument that was not UTF-8 (Python's
# surrogateescape): no text file can hold it.
_LABEL_BAD = re.compile('[/\\\\:*?"<>|,\x00-\x1f\x7f\ud800-\udfff]')
LABEL_RULE = ("1-64 characters of UTF-8 text, no space at either end, not starting with '.', "
              "none of / \\ : * ? \" < > | , tab or newline")


def check_label(label: str) -> str:
    """``label`` if it can name a class and a take's files anywhere, else :class:`RecordingError`
    stating :data:`LABEL_RULE`."""
    if (not isinstance(label, str) or not 1 <= len(label) <= 64 or label != label.strip()
            or label.startswith(".") or _LABEL_BAD.search(label)):
        raise RecordingError(f"label {label!r}: must be {LABEL_RULE}")
    return label


def class_key(label: str) -> str:
    """What makes two labels one class: labels equal once case-folded (``Paper``, ``paper``)
    or in one Unicode form (``café`` typed with an accented e or with an e and a combining
    accent: they look the same) would train as two classes of one surface, so a dataset's
    readers refuse them spelled two ways, and an importer refuses two materials that would
    give them."""
    return unicodedata.normalize("NFD", unicodedata.normalize("NFD", label).casefold())


class _KeyTwice(Exception):
    """A JSON object names a key twice."""


def _unique_keys(pairs: list[tuple[str, object]]) -> dict:
    """A JSON object whose keys are all different: a key given twice (an edit by hand, two
    files pasted together) would keep its last value and drop the other unseen."""
    out: dict = {}
    for key, value in pairs:
        if key in out:
            raise _KeyTwice(f"key {key!r} given twice in one object")
        out[key] = value
    return out


def read_meta(json_path: Path) -> tuple[dict, DeviceInfo]:
    """A take's JSON, checked key by key: (metadata, device header). Raises
    :class:`RecordingError` naming the file and the key."""
    try:
        text = json_path.read_bytes().decode("utf-8")
        meta = json.loads(text, object_pairs_hook=_unique_keys)
    except OSError as e:
        raise RecordingError(f"{json_path}: cannot read ({e.strerror or e})") from None
    except _KeyTwice as e:
        raise RecordingError(f"{json_path}: {e}") from None
    except (ValueError, RecursionError) as e:  # JSONDecodeError, bad UTF-8, too deep
        why = "nested too deeply" if isinstance(e, RecursionError) else str(e).splitlines()[0]
        raise RecordingError(f"{json_path}: not valid JSON ({why})") from None
    if isinstance(meta, dict) and (meta.get("format") != FORMAT
                                   or meta.get("version") not in READABLE_VERSIONS):
        raise RecordingError(
            f"{json_path}: not a {FORMAT} file of version "
            f"{' or '.join(map(str, READABLE_VERSIONS))} "
            f"(format={_shown(meta.get('format'))}, version={_shown(meta.get('version'))})")
    _check(meta, _META, "", json_path)
    try:  # the recorder's rule: a label names a class and files on any card
        check_label(meta["label"])
    except RecordingError as e:
        raise RecordingError(f"{json_path}: key 'label': {e}") from None
    _check(meta["device"], _DEVICE, "device", json_path)
    for i, ch in enumerate(meta["device"]["channels"]):
        _check(ch, _CHANNEL, f"device.channels[{i}]", json_path, closed=True)
    for i, g in enumerate(meta.get("gaps", [])):
        _check(g, _GAP, f"gaps[{i}]", json_path)
    try:
        info = DeviceInfo.from_dict(meta["device"])
    except (TactileError, ValueError, TypeError, OverflowError) as e:  # FrameError: its limits
        raise RecordingError(f"{json_path}: key 'device': {e}") from None
    _check_signals(meta.get("signals", {}), info.channel_names, json_path)
    return meta, info


def _check_signals(signals: dict, channels: tuple[str, ...], path: Path) -> None:
    """A take's high-rate signal declarations, ``{name: [channel, ...]}`` (the channels that
    hold one signal's consecutive sub-samples per frame, in time order): every channel is one
    of the take's, none is in two signals, no signal is named like a channel."""
    owner: dict[str, str] = {}
    for name, names in signals.items():
        if name in channels:
            raise RecordingError(f"{path}: key 'signals.{name}': a channel has that name")
        for c in names:
            if c not in channels:
                raise RecordingError(f"{path}: key 'signals.{name}': channel {c!r} is not one "
                                     "of the take's channels")
            if c in owner:
                raise RecordingError(f"{path}: key 'signals.{name}': channel {c!r} is in "
                                     f"signal {owner[c]!r} too")
            owner[c] = name


def signal_order_differs(declared: dict, signals, whose: str = "the model's") -> str | None:
    """Where a take's declared time order of a high-rate signal's sub-samples contradicts a
    model's. ``declared``: the take's ``signals`` (name -> channels in time order);
    ``signals``: the model's (``whose``, in the phrase), as (name, channels in time order)
    pairs. None when every pair of channels that both name is in the same order; else a phrase
    naming the first pair that is not. Channels are matched by name, so such a take would reach
    the model with each frame's sub-samples in another order: windows it would misread, without
    a word."""
    for model_name, channels in signals:
        for name, names in declared.items():
            at = {c: k for k, c in enumerate(names)}
            both = [c for c in channels if c in at]
            for a, b in zip(both, both[1:]):
                if at[a] > at[b]:
                    return (f"its signal {name!r} has {b} before {a}, {whose} signal "
                            f"{model_name!r} {a} before {b} (sub-samples in time order)")
    return None
