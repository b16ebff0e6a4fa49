"""tactile.device: wire protocol, simulated pen, recorder, recordings, firmware.

Importing it registers the ``sim://`` scheme with pyserial, so that
``serial.serial_for_url("sim://?texture=paper&seed=3")`` opens a simulated pen.
"""

import serial

if "tactile.device" not in serial.protocol_handler_packages:
    serial.protocol_handler_packages.append("tactile.device")
