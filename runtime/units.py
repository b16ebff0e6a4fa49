"""Counts to units: what the pen sends (int16 counts) to what the model takes (N, g, deg/s)."""

from __future__ import annotations

import numpy as np

from tactile.device.protocol import DeviceInfo


def to_units(info: DeviceInfo, raw: np.ndarray) -> np.ndarray:
    """Raw samples (n, C), as a :class:`~tactile.device.protocol.Samples` carries them (int16
    counts from binary frames, float64 values from CSV lines), to float32 values (n, C) in the
    channels' units, ``raw * scale + offset`` with each channel's scale and offset from the
    device's header (``info``: :class:`~tactile.device.protocol.DeviceInfo`). The model takes these.

    >>> from tactile.device.protocol import pen_info
    >>> to_units(pen_info(), np.array([[100, 100, 16384, 0, 0, 131, 0, 0]]))[0, :3]
    array([1., 1., 1.], dtype=float32)
    """
    scale = np.array([c.scale for c in info.channels], np.float64)
    offset = np.array([c.offset for c in info.channels], np.float64)
    return (raw * scale + offset).astype(np.float32)
