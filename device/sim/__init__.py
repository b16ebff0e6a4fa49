"""tactile.device.sim: the simulated pen.

:class:`PenSimulator` is a physical model of the pen stroked over one of :data:`TEXTURES` by a
simulated user (:class:`Session`); :class:`PenLink` sends its samples as the wire protocol, with
the faults a real cable has (:class:`LinkConfig`). The same pen is a pyserial port,
``serial.serial_for_url("sim://?texture=paper&seed=3")`` (the ``sim://`` handler,
:mod:`~tactile.device.sim.protocol_sim`, is registered by ``import tactile.device``), a
pseudo-terminal (:func:`serve_pty`) and a synthetic dataset (:func:`make_dataset`).
"""

from tactile.device.sim.dataset import make_dataset, take_seed
from tactile.device.sim.pty_server import serve_pty
from tactile.device.sim.session import Session
from tactile.device.sim.simlink import Injected, LinkConfig, PenLink
from tactile.device.sim.simulator import PenSimulator, simulate
from tactile.device.sim.textures import TEXTURES, TextureParams, texture_params

__all__ = [
    "TEXTURES", "Injected", "LinkConfig", "PenLink", "PenSimulator", "Session", "TextureParams",
    "make_dataset", "serve_pty", "simulate", "take_seed", "texture_params",
]
