"""tactile.device: wire protocol, simulated pen, recorder, recordings, firmware."""
