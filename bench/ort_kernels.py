"""Benchmark: the kernels inside onnxruntime (the ``ai.tactile`` nodes with the library
registered) against the same file's portable graphs and the references, one thread.

    python bench/ort_kernels.py [--repeats 5] [--no-label-time]

Cases, batch 1, the same windows for every implementation, all measured in this run
(interleaved rounds, the fastest round kept: :func:`bench.native.race`):

* EMD 1 x 1,100 samples, 8 IMFs x 10 sifts: the one-node EMD file with the library, the same
  file without it (its function: the portable graph), PyEMD;
* EMD 8 x 50 samples (the pen), 4 IMFs x 10 sifts: the same three;
* SparseCode of 46 rows x 176 features on 200 atoms, 17 non-zeros, float32: the one-node file
  with and without the library;
* the paper-size SF-RNN on BioTac finger 0 (``bench/label_time.py --paper-biotac 0``): time to
  label 1 s of data at hop 50 and at hop 5, with the library and with ``TACTILE_NATIVE=0``.

Issue targets: EMD 1 x 1,100 >= 25x PyEMD and >= 10x the portable graph; pen 8 x 50 >= 200x
PyEMD; SparseCode >= 10x the portable graph; SF-RNN finger 0 <= 3 ms per 1 s of data at hop 50.

Exit codes: 0 figures printed; 1 a bad argument, or no kernel library to time (not built, or
turned off with ``TACTILE_NATIVE``).
"""

from __future__ import annotations

import os
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from PyEMD import EMD as PyEMD
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parent))
from label_time import label_time, paper_biotac_file  # noqa: E402
from native import N_SIFTS, omp_rows, race, signal_windows  # noqa: E402

from tactile import native  # noqa: E402
from tactile.export.coder_graph import coder_node_model  # noqa: E402
from tactile.export.emd_graph import emd_node_model  # noqa: E402
from tactile.runtime import kernels  # noqa: E402
from tactile.training.sparse import SparseCoder  # noqa: E402


def _session(model: onnx.ModelProto, library: bool) -> ort.InferenceSession:
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    so.inter_op_num_threads = 1
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    if library:
        so.register_custom_ops_library(str(native.library_path()))
    return ort.InferenceSession(model.SerializeToString(), so,
                                providers=["CPUExecutionProvider"])


def table(title: str, ms: dict[str, float], base: str = "native node") -> list[str]:
    lines = [title, f"  {'implementation':<24} {'ms/call':>10} {'x ' + base:>15}"]
    lines += [f"  {name:<24} {t:>10.3f} {t / ms[base]:>15.1f}" for name, t in ms.items()]
    return lines


def emd_case(n_channels: int, n_time: int, n_imfs: int, repeats: int) -> list[str]:
    calls = 4 if n_time > 500 else 20
    x64 = signal_windows(calls, n_channels, n_time)
    x32 = x64.astype(np.float32)[:, None]  # (calls, 1, C, N): batch 1
    model = emd_node_model(n_imfs, N_SIFTS, n_channels, n_time)
    fast, slow = _session(model, True), _session(model, False)
    ref = PyEMD(FIXE=N_SIFTS, spline_kind="cubic", nbsym=2, extrema_detection="simple")

    def pyemd(i):
        for c in range(n_channels):
            ref.emd(x64[i, c], max_imf=n_imfs)

    fns = {"native node": lambda i: fast.run(None, {"x_in": x32[i]}),
           "portable graph": lambda i: slow.run(None, {"x_in": x32[i]}),
           "PyEMD": pyemd}
    return table(f"EMD {n_channels} x {n_time}, {n_imfs} IMFs x {N_SIFTS} sifts, batch 1, in "
                 "onnxruntime", race(fns, repeats, calls))


def code_case(repeats: int, rows: int = 46, features: int = 176, atoms: int = 200,
              n_nonzero: int = 17) -> list[str]:
    calls = 10
    d, x = omp_rows(calls, rows, features, atoms)
    model = coder_node_model(SparseCoder(d, n_nonzero))
    fast, slow = _session(model, True), _session(model, False)
    fns = {"native node": lambda i: fast.run(None, {"x": x[i]}),
           "portable graph": lambda i: slow.run(None, {"x": x[i]})}
    return table(f"SparseCode {rows} rows x {features} features, {atoms} atoms, {n_nonzero} "
                 "non-zeros, in onnxruntime", race(fns, repeats, calls))


def _with_hop(path: Path, hop: int, out: Path) -> Path:
    """A copy of ``path`` that runs at ``hop``: an edit by hand, so without the ``sha256`` key
    (the file's digest of itself)."""
    model = onnx.load(path)
    keep = [p for p in model.metadata_props if p.key != "sha256"]
    del model.metadata_props[:]
    model.metadata_props.extend(keep)
    for p in model.metadata_props:
        if p.key == "hop":
            p.value = str(hop)
    onnx.save(model, out)
    return out


def label_case(rounds: int) -> list[str]:
    tmp = Path(tempfile.mkdtemp())
    base = paper_biotac_file("0", tmp / "sf_rnn-f0.onnx")
    lines = ["SF-RNN, paper sizes, BioTac finger 0: ms of CPU to label 1 s of data, batch 1"]
    lines.append(f"  {'hop':<6} {'native':>10} {'TACTILE_NATIVE=0':>18} {'ratio':>8}")
    for hop in (50, 5):
        path = base if hop == 50 else _with_hop(base, hop, tmp / f"sf_rnn-f0-hop{hop}.onnx")
        kernels._state.update(disabled=False, said=False)
        seconds = 0.4 * hop  # 40 windows at either hop: the same Gaussian windows
        fast = label_time(path, seconds=seconds, rounds=rounds)["ms_per_s"]
        os.environ["TACTILE_NATIVE"] = "0"
        try:
            slow = label_time(path, seconds=seconds, rounds=rounds)["ms_per_s"]
        finally:
            del os.environ["TACTILE_NATIVE"]
        lines.append(f"  {hop:<6} {fast:>10.2f} {slow:>18.2f} {slow / fast:>8.1f}")
    return lines


def main(argv: list[str] | None = None) -> int:
    from tactile.cli import Parser, int_in

    parser = Parser(prog="ort_kernels.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int_in(1), default=5,
                        help="timed rounds, the fastest kept (default 5)")
    parser.add_argument("--no-label-time", action="store_true", help="skip the SF-RNN case")
    args = parser.parse_args(argv)
    if not native.available():
        why = ("turned off by TACTILE_NATIVE" if native.disabled_by_env() else
               "not built: pip install -e . with a C compiler")
        print(f"ort_kernels.py: error: no kernel library to time ({why})", file=sys.stderr)
        return 1
    torch.set_num_threads(1)
    warnings.simplefilter("ignore", RuntimeWarning)
    print(f"onnxruntime {ort.__version__}, library {native.library_path().name}, one thread",
          file=sys.stderr)
    with threadpool_limits(1):
        lines = emd_case(1, 1100, 8, args.repeats) + emd_case(8, 50, 4, args.repeats)
        lines += code_case(args.repeats)
        if not args.no_label_time:
            lines += label_case(args.repeats)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
