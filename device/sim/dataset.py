"""A synthetic dataset: takes of the simulated pen, one simulated user per take index.

    make_dataset(Path("data/sim"), takes=20)   # 20 takes x 7 textures, as fast as it can
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import zlib
from collections.abc import Callable
from pathlib import Path

from tactile.device.recordings.take import dataset_folder, replace_takes, whole_take
from tactile.device.recordings.writer import TakeWriter
from tactile.device.sim.simulator import TEXTURES, PenSimulator
from tactile.errors import ConfigError


def take_seed(base: int, texture: str, take: int) -> int:
    """A stable seed per (texture, take): the same dataset whatever else is generated."""
    return (base * 1_000_003 + zlib.crc32(texture.encode()) * 1009 + take) % 2**31


def make_dataset(
    out: Path,
    takes: int,
    textures: tuple[str, ...] = TEXTURES,
    seconds: float = 60.0,
    seed: int = 0,
    rate_hz: float = 100.0,
    first_take: int = 0,
    force: bool = False,
    written: Callable[[Path], object] | None = None,
) -> list[Path]:
    """Write ``takes`` takes per texture; take k of every texture is simulated user k.

    Takes are named ``<texture>-user<k>``: a folder that already holds one of them is refused
    (so that a second run neither overwrites nor duplicates a dataset), unless ``force``, which
    replaces those takes. Other takes in the folder are left alone (``first_take`` adds users).
    ``written(path)``, when given, is called as each take is whole (its ``.csv``).
    """
    if not textures:
        raise ConfigError(f"no texture given: give one or more of {', '.join(TEXTURES)}")
    for i, t in enumerate(textures):
        if t not in TEXTURES:
            raise ConfigError(f"texture {t!r}: must be one of {', '.join(TEXTURES)}")
        if t in textures[:i]:  # its takes would be the same users' again, byte for byte
            raise ConfigError(f"texture {t!r} given twice")
    if takes < 1 or not seconds > 0:
        raise ConfigError(f"--takes {takes} and --seconds {seconds}: must be >= 1 and > 0")
    if not math.isfinite(seconds):  # --pty streams until stopped; a take has an end
        raise ConfigError(f"--seconds {seconds}: a take needs a finite length")
    samples = seconds * rate_hz
    if not math.isfinite(samples):
        raise ConfigError(f"--seconds {seconds:g} at {rate_hz:g} Hz: more samples than a take "
                          "can count")
    if round(samples) < 1:
        raise ConfigError(f"--seconds {seconds} at {rate_hz:g} Hz: not one sample a take")
    n = round(samples)
    # refuse a dataset that cannot fit before writing any of it (--seconds 1e300 would fill
    # the disk a take at a time)
    need = min(takes * len(textures) * least_take_bytes(seconds, rate_hz), 1e308)  # not inf
    there = next((p for p in (Path(out), *Path(out).parents) if p.is_dir()), Path("."))
    free = shutil.disk_usage(there).free
    if need > free and shutil.disk_usage(there).total > 0:  # (/proc has no disk: not "full")
        raise ConfigError(f"--seconds {seconds:g} x {takes * len(textures)} takes at "
                          f"{rate_hz:g} Hz: at least {_size(need)}, and the disk of {out} has "
                          f"{_size(free)} free")
    out = dataset_folder(out)
    replace_takes(out, [f"{t}-user{k:03d}" for k in range(first_take, first_take + takes)
                        for t in textures], force,
                  PenSimulator(textures[0], seed=0, rate_hz=rate_hz).info)
    paths = []
    for k in range(first_take, first_take + takes):
        for texture in textures:
            s = take_seed(seed, texture, k)
            sim = PenSimulator(texture, seed=s, rate_hz=rate_hz)
            extra = {
                "user": k,
                "simulator": {"texture": texture, "seed": s,
                              "session": dataclasses.asdict(sim.session)},
            }
            name = f"{texture}-user{k:03d}"
            with whole_take(out, name, force, done=written), TakeWriter(
                    out, texture, sim.info, "simulator", name=name, extra=extra,
                    exact=True) as w:
                for start in range(0, n, 6000):
                    raw = sim.read(min(6000, n - start))
                    w.write(start, round(start * 1e6 / rate_hz), raw)
            paths.append(w.csv_path)
    return paths


def least_take_bytes(seconds: float, rate_hz: float) -> float:
    """Fewer bytes than a simulated take of ``seconds`` at ``rate_hz`` writes: each CSV row
    holds at least 30 bytes of samples and the digits of its counters, here those of the last
    row (seq and t_us) less one each. A float: inf for a take too long to write."""
    samples = seconds * rate_hz
    digits = math.floor(math.log10(samples)) + math.floor(math.log10(seconds) + 6)
    return samples * (30 + digits)


def _size(n: float) -> str:
    """``n`` bytes in the largest unit that keeps it >= 1 (``12.3 GB``)."""
    units = ("bytes", "kB", "MB", "GB", "TB", "PB")
    k = 0
    while n >= 1000 and k < len(units) - 1:
        n, k = n / 1000, k + 1
    return f"{n:.0f} bytes" if k == 0 else f"{n:.3g} {units[k]}"


__all__ = ["least_take_bytes", "make_dataset", "take_seed"]
