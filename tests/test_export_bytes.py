"""An export of the same checkpoint is the same file, byte for byte.

Three model families, each a checkpoint written here from seeded untrained weights (no
training run, so the file depends on the export code alone): the default ``lstm`` with its
spectral front end, an ``lstm`` with EMD features, and a granular ``sf_rnn`` with sparse
codes (two EMDs at different rates, learned-dictionary coders). Each is exported by
``export_run`` as ``tactile-export`` does (graph, parity figures, metadata) and its sha256
compared with ``export_bytes.json``, goldens made by an earlier version of the export code:
an independent reference for changes that must not change the graph. The hash leaves out the
parity figures, which onnxruntime measures on the machine at hand (:data:`MEASURED`).

The goldens hold for the torch, onnx and onnxruntime versions they were made with (the
serialisation and the parity figures may differ across versions): with others installed,
that comparison skips and says why. The comparison of two exports of one checkpoint never
skips.

When the graph changes on purpose, regenerate the goldens (and say why in the commit)::

    python tests/test_export_bytes.py --write
"""

from __future__ import annotations

import hashlib
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import onnx
import onnxruntime
import pytest
import torch

import tactile
from tactile.device.protocol.info import PEN_CHANNELS
from tactile.export.exporter import export_run
from tactile.training.checkpoint import CHECKPOINT, CHECKPOINT_FORMAT, CHECKPOINT_VERSION
from tactile.training.config import TrainConfig
from tactile.training.models import build_model

GOLDENS = Path(__file__).with_name("export_bytes.json")
PEN = [c.name for c in PEN_CHANNELS]
SIGNAL = ["sig_0", "sig_1", "sig_2", "sig_3"]
GRANULAR = [*SIGNAL, "pdc", "ele_0", "ele_1"]
RUNS = {  # name -> (config, channels)
    "lstm-spectral": ({"layers": 1, "hidden": 8}, PEN),
    "lstm-emd": ({"layers": 2, "hidden": 8, "emd_imfs": 2, "emd_sifts": 3,
                  "emd_channels": ["accel_z"]}, PEN),
    "sf_rnn-codes": ({"model": "sf_rnn", "window": 20, "hop": 10, "layers": 1, "hidden": 8,
                      "emd_sifts": 4, "signals": {"sig": SIGNAL},
                      "modalities": {
                          "vibration": {"channels": ["sig"], "imfs": 2, "steps": 6,
                                        "atoms": 12, "nonzero": 2},
                          "pressure": {"channels": ["pdc"], "imfs": 2, "steps": 3,
                                       "atoms": 8, "nonzero": 1},
                          "electrodes": {"channels": ["ele_*"], "imfs": 0, "steps": 3,
                                         "atoms": 8, "nonzero": 2}}}, GRANULAR),
}


def write_checkpoint(name: str, run: Path) -> Path:
    """Run folder ``run`` holding a checkpoint of run ``name``: seeded, untrained weights (and
    seeded random dictionaries for a coded model), the keys tactile-train writes."""
    overrides, channels = RUNS[name]
    cfg = TrainConfig.from_dict({"seed": 0, "threads": 1, **overrides, "channels": channels})
    n = len(channels)
    rng = np.random.default_rng(7)
    mean = rng.uniform(-1, 1, n).round(3)
    std = rng.uniform(0.5, 2, n).round(3)
    emd_index = [channels.index(c) for c in cfg.emd_channels]
    center = [] if cfg.modalities else [i for i, c in enumerate(channels) if c.startswith("acc")]
    torch.manual_seed(0)
    model = build_model(cfg, 3, torch.tensor(mean), torch.tensor(std), channels=tuple(channels),
                        rate_hz=100.0, emd_index=emd_index, center_index=center)
    if getattr(model.pre, "needs_dictionaries", False):
        dicts = []
        for m in model.layout:
            d = rng.standard_normal((m.atoms, m.features)).astype(np.float32)
            dicts.append(d / np.linalg.norm(d, axis=1, keepdims=True))
        model.pre.set_dictionaries(dicts)
    run.mkdir(parents=True, exist_ok=True)
    ck = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "package_version": tactile.__version__,
        "config": cfg.to_dict(),
        "classes": ["coarse", "fine", "smooth"] if cfg.modalities else ["desk", "paper", "wood"],
        "channels": list(channels),
        "units": ["count"] * n if cfg.modalities else [c.unit for c in PEN_CHANNELS],
        "sample_rate_hz": 100.0,
        "mean": mean.tolist(),
        "std": std.tolist(),
        "emd_index": emd_index,
        "center_index": center,
        "metrics": {"accuracy": 0.5},
        "state_dict": model.state_dict(),
    }
    torch.save(ck, run / CHECKPOINT)
    return run


MEASURED = ("parity", "sha256")
"""Metadata keys the hash leaves out: ``parity``, the figures onnxruntime measured on this
machine (its float32 kernels differ by instruction set: the same versions gave other last
digits of a granular model's differences on an AVX-512 processor than on another), which the
parity tests check; and ``sha256``, the file's digest of itself, a function of the rest
(checked in ``test_export.py``)."""


def export_sha256(run: Path, out: Path) -> str:
    """sha256 of the .onnx file ``export_run`` writes for ``run``, without the
    :data:`MEASURED` metadata keys: the graph and every other key."""
    torch.set_num_threads(1)
    export_run(run, out, log=lambda s: None)
    model = onnx.load_model_from_string(out.read_bytes())
    assert model.metadata_props[-1].key == "sha256"
    kept = [p for p in model.metadata_props if p.key not in MEASURED]
    assert len(kept) == len(model.metadata_props) - len(MEASURED)
    del model.metadata_props[:]
    model.metadata_props.extend(kept)
    return hashlib.sha256(model.SerializeToString()).hexdigest()


def versions() -> dict[str, str]:
    """The versions the goldens depend on: the serialisation (torch, onnx), onnxruntime (the
    exporter's checks run in it) and whether the native kernels are built (the exporter checks
    the kernel path too)."""
    from tactile import native

    return {"torch": torch.__version__, "onnx": onnx.__version__,
            "onnxruntime": onnxruntime.__version__,
            "native_kernels": "built" if native.available() else "absent"}


_SHA: dict[str, str] = {}


def _sha(name: str, root: Path) -> str:
    """The export's sha256 of run ``name``, once per session (the run folder is always named
    ``name``: the metadata records it)."""
    if name not in _SHA:
        _SHA[name] = export_sha256(write_checkpoint(name, root / name), root / f"{name}.onnx")
    return _SHA[name]


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("bytes")


@pytest.mark.parametrize("name", sorted(RUNS))
def test_export_matches_golden(name, root):
    goldens = json.loads(GOLDENS.read_text())
    if goldens["versions"] != versions():
        pytest.skip(f"goldens made with {goldens['versions']}, installed {versions()}: "
                    "serialisation may differ across versions")
    assert _sha(name, root) == goldens["sha256"][name], (
        f"{name}: the export changed; if on purpose, regenerate the goldens (module docstring)")


def test_two_exports_are_identical(root, tmp_path):
    name = "lstm-emd"
    again = tmp_path / name
    assert export_sha256(write_checkpoint(name, again), tmp_path / f"{name}.onnx") == _sha(
        name, root)


def main(argv: list[str]) -> int:
    """``--write``: regenerate the goldens; else print the sha256s."""
    with tempfile.TemporaryDirectory() as tmp:
        shas = {n: export_sha256(write_checkpoint(n, Path(tmp) / n), Path(tmp) / f"{n}.onnx")
                for n in sorted(RUNS)}
    doc = {"about": "sha256 of tactile-export's file for each run of tests/test_export_bytes.py, "
                    "made with these versions; regenerate with "
                    "'python tests/test_export_bytes.py --write' when the graph changes on "
                    "purpose",
           "versions": versions(), "sha256": shas}
    if "--write" in argv:
        GOLDENS.write_text(json.dumps(doc, indent=1) + "\n")
    print(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
