"""tactile: pen-type touch sensor toolkit (device -> training -> export -> runtime)."""

__version__ = "0.1.0"
