"""A run's checkpoint to one checked ONNX file (what ``tactile-export`` does).

Builds the graph (preprocessing + model + state), measures parity against PyTorch on the run's
test windows (``--data``; else a simulated pen, else random windows), refuses to write a file
that fails it, and writes the contract into the file's metadata. ``--int8`` writes an
onnxruntime dynamic-int8 file instead and reports its size, latency and accuracy against the
float32 one.
"""

from __future__ import annotations

import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import onnx

from tactile import checksum
from tactile.errors import ConfigError, ModelContractError
from tactile.export.calibrate import calibrate_file
from tactile.export.check import load_contract
from tactile.export.custom_ops import custom_nodes, custom_ops_key
from tactile.export.graph import build_graph
from tactile.export.metadata import attach, contract_for
from tactile.export.parity import Parity, ParityError, compare, compare_on_kernels
from tactile.export.quantize import latency_ms, quantize_int8
from tactile.export.session import native_available
from tactile.export.windows import probe_windows
from tactile.files import output_error
from tactile.training.checkpoint import load_checkpoint


def export_run(run_dir: Path, out: Path, data: Path | None = None, int8: bool = False,
               max_windows: int = 256, log=print) -> dict:
    """Export ``run_dir`` to ``out``; returns the figures (parity, sizes, seconds).

    Raises :class:`ParityError` (after logging the figures) when parity fails.
    """
    t0 = time.perf_counter()
    run_dir, out = Path(run_dir), output_file(out)
    model, ck = load_checkpoint(run_dir)
    graph = build_graph(model)
    t_build = time.perf_counter() - t0
    probe = probe_windows(ck, data, max_windows)
    parity = compare(model, graph.SerializeToString(), probe, ck)
    custom = custom_nodes(graph)  # two paths through the file: each table names its own
    log(("portable graph:\n" if custom else "") + parity.table())
    _require(parity, "float32")
    report = {"build_s": round(t_build, 2), "parity": parity.to_dict()}
    final, quantization, figures = graph, "none", parity.to_dict()
    if custom and native_available():  # the same file on the kernels: it must pass too
        fast = compare_on_kernels(model, graph, probe, ck, "strict")
        log("native kernels:\n" + fast.table())
        _require(fast, "float32 (native kernels)")
        figures = {**figures, "native": fast.to_dict()}
        report["parity_native"] = fast.to_dict()
    if int8:
        final = quantize_int8(graph)
        q = compare(model, final.SerializeToString(), probe, ck, criterion="int8")
        log(("int8, portable graph:\n" if custom else "int8:\n") + q.table())
        _require(q, "int8")
        q_fast = None
        if custom_nodes(final) and native_available():
            q_fast = compare_on_kernels(model, final, probe, ck, "int8")
            log("int8, native kernels:\n" + q_fast.table())
            _require(q_fast, "int8 (native kernels)")
            report["int8_native"] = q_fast.to_dict()
        figures = {**q.to_dict(), "float32": parity.to_dict()}
        if q_fast is not None:  # the file's figures on the kernels, as a float32 file has them
            figures["native"] = q_fast.to_dict()
        quantization = "int8-dynamic"
        report["int8"] = _tradeoff(graph, final, parity, q, ck, model.state_shape)
        log(_tradeoff_line(report["int8"]))
    contract = contract_for(ck, figures, quantization, run_dir.resolve().name, model)
    if custom_nodes(final):
        contract = replace(contract, extra={**contract.extra, "custom_ops": custom_ops_key(final)})
    attach(final, contract)
    report["postprocess"] = calibrate_file(final, ck, model.cfg, data, log)
    # the last key: the file's own digest, so that a damaged copy is refused (tactile.checksum)
    onnx.helper.set_model_props(final, {**{p.key: p.value for p in final.metadata_props},
                                        checksum.KEY: checksum.PLACEHOLDER})
    try:
        with tempfile.NamedTemporaryFile(dir=out.parent, suffix=".onnx", delete=False) as tmp:
            tmp_path = Path(tmp.name)
    except OSError as e:  # the folder went away or filled up since output_file looked
        raise output_error(f"-o {out}: cannot write in {out.parent}", e) from None
    try:
        try:
            tmp_path.write_bytes(checksum.seal(final.SerializeToString()))
        except OSError as e:  # a full disk: named as the file it was to be
            raise output_error(f"-o {out}: cannot be written", e) from None
        try:  # the written file honours the contract, or nothing is written
            load_contract(tmp_path)
        except ModelContractError as e:  # named as the file it was to be, not the temp file
            raise ModelContractError(str(e).replace(str(tmp_path), str(out))) from None
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(tmp_path, 0o666 & ~mask)  # a temp file is private; the model is not
        tmp_path.replace(out)
    finally:
        tmp_path.unlink(missing_ok=True)
    report.update(seconds=round(time.perf_counter() - t0, 2), bytes=out.stat().st_size)
    return report


def output_file(out: Path) -> Path:
    """``out`` as the file to write, checked before any work: a name ending in ``.onnx``, not
    a folder, in a folder that exists (nothing is created that the user did not ask for).
    :class:`ConfigError` otherwise."""
    out = Path(out)
    if out.is_dir():
        raise ConfigError(f"-o {out}: a folder; give the file to write, e.g. {out / 'model.onnx'}")
    if out.suffix.lower() != ".onnx":  # e.g. -o RUN/checkpoint.pt would replace the run
        raise ConfigError(f"-o {out}: name an .onnx file, e.g. {out.with_suffix('.onnx')}")
    if not out.parent.is_dir():
        raise ConfigError(f"-o {out}: no folder {out.parent} to write it in")
    try:  # tried, not asked: os.access says yes to root, also on /proc or a read-only mount
        with tempfile.NamedTemporaryFile(dir=out.parent, suffix=".onnx"):
            pass
    except OSError as e:
        raise ConfigError(f"-o {out}: cannot write in {out.parent} ({e.strerror or e})") from None
    return out


def _require(p: Parity, what: str) -> None:
    if not p.passed:
        raise ParityError(f"{what} parity failed: {'; '.join(p.failures())}")


def _tradeoff(f32: onnx.ModelProto, q: onnx.ModelProto, pf: Parity, pq: Parity, ck: dict,
              state: tuple[int, int]) -> dict:
    """Sizes, batch-1 latency on the path ``tactile-run`` takes here (the kernels when the
    file has custom nodes and they are built), agreement and accuracy of the two files."""
    args = (ck["config"]["window"], len(ck["channels"]), state)
    native = bool(custom_nodes(f32)) and native_available()
    return {
        "bytes_float32": f32.ByteSize(), "bytes_int8": q.ByteSize(),
        "latency_float32": latency_ms(f32.SerializeToString(), *args, native=native),
        "latency_int8": latency_ms(q.SerializeToString(), *args, native=native),
        "latency_path": "native kernels" if native else (
            "portable graph" if custom_nodes(f32) else "standard operators"),
        "label_agreement": pq.label_agreement, "max_abs_prob_diff": pq.max_abs_prob_diff,
        "accuracy_float32": pf.accuracy_onnx, "accuracy_int8": pq.accuracy_onnx,
    }


def _tradeoff_line(t: dict) -> str:
    acc = ""
    if t["accuracy_int8"] is not None:
        acc = f"; accuracy {t['accuracy_float32']:.4f} -> {t['accuracy_int8']:.4f}"
    return (f"int8 trade-off: graph size (without the metadata) "
            f"{t['bytes_float32'] / 1e3:.1f} kB -> {t['bytes_int8'] / 1e3:.1f} kB; "
            f"batch-1 latency p50 ({t['latency_path']}) "
            f"{t['latency_float32']['p50_ms']:.3f} -> {t['latency_int8']['p50_ms']:.3f} ms; "
            f"label agreement with PyTorch {t['label_agreement']:.4f}{acc}")


__all__ = ["export_run", "output_file"]
