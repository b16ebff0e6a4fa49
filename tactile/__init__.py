"""tactile: pen-type touch sensor toolkit (device -> training -> export -> runtime)."""

import os as _os

__version__ = "0.1.0"

# In a clone, the stages' folders (runtime/, training/, export/, device/) sit beside this one,
# not in it: an installed copy holds them here. Python started in the clone's root finds this
# folder first (the current folder comes first on sys.path), so without them `import
# tactile.runtime` would fail there while an installed tactile would serve it. The clone's root
# then joins the search path of this package: the clone imports whole, as its own code. (An
# editable install of the clone finds the same files either way.)
_here = _os.path.dirname(_os.path.abspath(__file__))
_root = _os.path.dirname(_here)
if not _os.path.isdir(_os.path.join(_here, "runtime")) and _os.path.isfile(
        _os.path.join(_root, "runtime", "__init__.py")):
    __path__.append(_root)  # noqa: F821 (a package's __path__)
