"""The runtime's command lines, each a thin module over the library: ``tactile-run``
(:mod:`.run`) and ``tactile-monitor`` (:mod:`.monitor`)."""

__all__ = ["monitor", "run"]
