"""The export stage's commands: ``export`` (``tactile-export``), ``check`` (``tactile-check``).

Each is a thin module over the library (:mod:`tactile.export.exporter`,
:mod:`tactile.export.check`): its top imports only the standard library and :mod:`tactile.cli`.
"""
