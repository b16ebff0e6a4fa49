"""The textures the simulated pen is stroked over, and what its tip feels on each.

The classes are :data:`TEXTURES`, in class order: the surfaces of ``textures.toml`` (shipped
beside this module, read once at import), then ``non_contact`` (the pen in the air).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, fields
from importlib import resources

from tactile.device.sim.pen import MOVING_MASS, TIP_STIFFNESS
from tactile.errors import ConfigError


@dataclass(frozen=True)
class TextureParams:
    """What the tip feels on one surface (``textures.toml`` gives the numbers and where they
    come from).

    ``roughness_um``/``corr_mm``: RMS height (um) and correlation length (mm) of the random
    part of the height profile; ``period_mm``/``period_um``: wavelength and amplitude of a
    periodic part (0 = none); ``patch_mm``: contact patch radius, which smooths features shorter
    than it; ``mu_kinetic``/``mu_static``: friction of the rubber tip on it; ``stick_speed``:
    m/s below which the contact sticks and slips; ``mu_variation``: RMS
    variation of the friction coefficient along the path; ``grain``: RMS normal-force ripple
    per newton of push from single asperities and fibres (what the rubber sensor feels most
    directly); ``stiffness``: N/m of the surface layer under
    the tip; ``damping``: damping ratio of the tip-on-surface contact; ``creep_s``: time
    constant of the layer's viscoelastic creep (foam, fibre pile): the push builds up at the tip
    this much later, and faster push changes (tremor, push/pull steps) are smoothed.
    """

    roughness_um: float
    corr_mm: float
    period_mm: float
    period_um: float
    patch_mm: float
    mu_kinetic: float
    mu_static: float
    stick_speed: float
    mu_variation: float
    grain: float
    stiffness: float
    damping: float
    creep_s: float

    @property
    def contact_stiffness(self) -> float:
        """N/m of the tip and the surface in series."""
        return 1.0 / (1.0 / TIP_STIFFNESS + 1.0 / self.stiffness)

    @property
    def contact_hz(self) -> float:
        """Natural frequency of the moving mass on the contact stiffness (Hz)."""
        return math.sqrt(self.contact_stiffness / MOVING_MASS) / (2.0 * math.pi)


def _load_table() -> dict[str, TextureParams]:
    """``textures.toml``: one table per surface, every field of :class:`TextureParams`, numbers
    only."""
    text = resources.files(__package__).joinpath("textures.toml").read_text(encoding="utf-8")
    names = [f.name for f in fields(TextureParams)]
    table = {}
    for texture, values in tomllib.loads(text).items():
        if sorted(values) != sorted(names):
            raise ConfigError(f"textures.toml [{texture}]: needs exactly the keys "
                              f"{', '.join(names)}")
        table[texture] = TextureParams(**{k: float(values[k]) for k in names})
    return table


_TEXTURE_TABLE: dict[str, TextureParams] = _load_table()

TEXTURES: tuple[str, ...] = (*_TEXTURE_TABLE, "non_contact")


def texture_params(texture: str) -> TextureParams | None:
    """The contact parameters of ``texture``; ``None`` for ``non_contact``."""
    _check_texture(texture)
    return _TEXTURE_TABLE.get(texture)


def _check_texture(texture: str) -> None:
    if texture not in TEXTURES:
        raise ConfigError(f"unknown texture {texture!r}: expected one of {', '.join(TEXTURES)}")


__all__ = ["TEXTURES", "TextureParams", "texture_params"]
