"""tactile.device.commands: the device stage's command lines, one module each.

``tactile-sim`` (:mod:`.sim`), ``tactile-record`` (:mod:`.record`), ``tactile-ports``
(:mod:`.ports`), ``tactile-import-hapmat`` (:mod:`.import_hapmat`), ``tactile-import-biotac``
(:mod:`.import_biotac`), ``tactile-data`` (:mod:`.data`) and ``tactile-plot`` (:mod:`.plot`).
Each is a thin ``main(argv=None)`` that parses its arguments and then imports the library it
drives, so that a missing optional extra is one line, not a traceback.
"""
