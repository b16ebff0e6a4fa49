"""Settings given as ``KEY=VALUE`` text (``tactile-train --set``, the benchmark scripts)."""

from __future__ import annotations

from tactile.errors import ConfigError
from tactile.training.config import TrainConfig


def parse_sets(pairs: list[str], base: TrainConfig) -> TrainConfig:
    """``key=value`` overrides, typed like the field they set."""
    d = base.to_dict()
    for pair in pairs:
        key, sep, value = pair.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ConfigError(f"--set {pair!r}: expected KEY=VALUE")
        if key not in d:
            raise ConfigError(f"--set {key}: unknown setting; allowed: {sorted(d)}")
        if key in ("signals", "modalities"):
            raise ConfigError(f"--set {key}: a table ([{key}...]): give it in the --config file")
        current = getattr(TrainConfig, key)
        try:
            if isinstance(current, tuple):
                d[key] = [v for v in value.split(",") if v]
            elif isinstance(current, bool):
                d[key] = {"true": True, "on": True, "1": True,
                          "false": False, "off": False, "0": False}[value.lower()]
            elif isinstance(current, int):
                d[key] = int(value)
            elif isinstance(current, float):
                d[key] = float(value)
            else:
                d[key] = value
        except (ValueError, KeyError):
            kind = ("on/off, true/false or 1/0" if isinstance(current, bool)
                    else f"a valid {type(current).__name__}")
            raise ConfigError(f"--set {key}={value!r}: not {kind}") from None
    return TrainConfig.from_dict(d)


__all__ = ["parse_sets"]
