"""The native kernel library in the runtime's onnxruntime sessions.

An exported file holds each EMD and each sparse coder as one ``ai.tactile`` node with a
model-local function as its portable fallback (``docs/export.md``). Registered in a session's
options, the package's kernel library (``tactile/native``, built where the install had a C
compiler) runs those nodes in C; without it onnxruntime runs the functions, the standard-op
graphs: the same EMD (float64 on both paths), the same codes but where float32 rounding decides
a near-tie of two atoms (``docs/export.md``). :func:`library_path` says which:
``TACTILE_NATIVE=0`` in the environment (or ``false``, ``off``, ``no``), or :func:`disable`
(``--no-native`` on tactile-run and tactile-check), forces the portable graphs. No torch, no
onnx: numpy and onnxruntime only.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from tactile.contract import CUSTOM_DOMAIN

_state = {"disabled": False, "said": False}


def disable() -> None:
    """Run the portable graphs in every session made after this call (``--no-native``)."""
    _state["disabled"] = True


def _disabled() -> bool:
    from tactile import native

    return _state["disabled"] or native.disabled_by_env()


def library_path() -> Path | None:
    """The built kernel library's path, or None: not built (no C compiler at install time),
    ``TACTILE_NATIVE`` off (``0``, ``false``, ``off``, ``no``), or :func:`disable` called."""
    if _disabled():
        return None
    from tactile import native

    return native.library_path()


def has_custom_nodes(path: str | os.PathLike) -> bool:
    """Whether a node of the file (in its graph, a subgraph or a function's body) is in the
    ``ai.tactile`` domain: a byte search, since the runtime has no onnx package to parse the
    file with, for the domain as a node's field 7 (protobuf tag 0x3a, then its length), not as
    an opset import or a function's domain, which a file without such nodes may name too. A
    text field holding ``":\nai.tactile"`` would match as well: the library is then
    registered for nothing, and no result changes."""
    domain = CUSTOM_DOMAIN.encode()  # under 128 bytes: its length is one varint byte
    try:
        return bytes([0x3A, len(domain)]) + domain in Path(path).read_bytes()
    except OSError:
        return False


def register(options, path: str | os.PathLike) -> bool:
    """Register the kernel library in ``options`` (an ``onnxruntime.SessionOptions``) when the
    file at ``path`` has custom nodes and the library is there; True when registered. When
    the file has custom nodes and the library is not used, say once on stderr that the
    portable graphs run."""
    if not has_custom_nodes(path):
        return False
    lib = library_path()
    if lib is not None:
        try:
            options.register_custom_ops_library(str(lib))
            return True
        except Exception as e:  # noqa: BLE001  (onnxruntime's untyped errors)
            reason = f"the kernel library did not load ({str(e).strip().splitlines()[0]})"
    elif _disabled():
        reason = "native kernels disabled"
    else:
        reason = "no kernel library: the package was installed without a C compiler"
    if not _state["said"]:
        _state["said"] = True
        from tactile.cli import prefix  # the command's name while one runs

        print(f"{prefix('tactile: ')}running the portable EMD/sparse-code graphs ({reason})",
              file=sys.stderr)
    return False


def paths(custom_ops: list[dict], registered: bool) -> list[str]:
    """One line per custom op type of a file: ``EMD: native kernel`` or ``EMD: portable graph
    (...)``, as this process runs it (``registered``: the session has the library). A file
    without custom ops needs no kernel: one line saying so and whether the library is here
    (a board's install can be checked with any model file)."""
    ops = list(dict.fromkeys(c["op"] for c in custom_ops))
    if not ops:
        lib = library_path()
        return ["none needed by this file (no EMD or sparse-code node); " + (
            f"the kernel library is built ({lib.name})" if lib is not None else
            "native kernels disabled" if _disabled() else
            "no kernel library: the package was installed without a C compiler")]
    if registered:
        how = "native kernel"
    elif _disabled():
        how = "portable graph (native kernels disabled)"
    else:
        how = "portable graph (no kernel library)"
    return [f"{op}: {how}" for op in ops]


__all__ = ["disable", "has_custom_nodes", "library_path", "paths", "register"]
