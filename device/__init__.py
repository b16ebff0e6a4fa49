"""tactile.device: the pen and everything that reads it, by job.

* :mod:`tactile.device.protocol`: the wire protocol (frames, codec, the stream decoder);
* :mod:`tactile.device.link`: the serial link (ports, the one read/reconnect loop);
* :mod:`tactile.device.sim`: the simulated pen (physics, link faults, the ``sim://`` port);
* :mod:`tactile.device.recordings`: the take format and what reads or writes takes (recorder,
  importers, dataset summary and plots);
* :mod:`tactile.device.commands`: the command lines; ``device/firmware``: the pen's firmware.

Importing it registers the ``sim://`` scheme with pyserial, so that
``serial.serial_for_url("sim://?texture=paper&seed=3")`` opens a simulated pen (pyserial imports
``tactile.device.sim.protocol_sim`` for it).
"""

import serial

if "tactile.device.sim" not in serial.protocol_handler_packages:
    serial.protocol_handler_packages.append("tactile.device.sim")
