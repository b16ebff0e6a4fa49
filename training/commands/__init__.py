"""The training stage's commands: ``tactile-train`` (:mod:`.train`) and ``tactile-eval``
(:mod:`.eval`). Each module imports only the standard library and :mod:`tactile.cli` at its
top, and the library it drives inside ``main``."""
