"""Is this file a model we can deploy? The checks of ``tactile-check``.

:func:`load_contract` validates the contract of any ONNX file (an ONNX model at all,
``onnx.checker``, opset, input and output names, dtypes, ranks, the dynamic batch axis, every
required metadata key) and names what is wrong in one line (:class:`ModelContractError`, exit
code 3). :func:`check_file` adds, given a run, the parity comparison against the run's PyTorch
model (on a dataset's test windows if given, else simulated or random ones), printing the
table; given a dataset alone, it runs the file on the data's windows (the run's test split
when the data holds its test takes, recognised by content, else every take, and it says which)
and prints the accuracy beside the one training recorded, saying what that was measured on.

On a board (no ``[train]`` extra: no onnx, no torch) it checks what the runtime will: loads the
file with onnxruntime, validates the contract and the graph's signature as ``tactile-run`` does,
and runs one window through it (:func:`board_check`); a run or a dataset needs the extra.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from tactile import checksum
from tactile.cli import holding_signals
from tactile.contract import OPSET, ModelContract, model_file
from tactile.errors import ConfigError, ModelContractError

if TYPE_CHECKING:
    import onnx

# onnx TensorProto element types as onnxruntime spells them (the contract's spelling)
_TYPES = {1: "tensor(float)", 2: "tensor(uint8)", 3: "tensor(int8)", 6: "tensor(int32)",
          7: "tensor(int64)", 9: "tensor(bool)", 10: "tensor(float16)", 11: "tensor(double)"}


def load_contract(path: str | Path) -> tuple[onnx.ModelProto, ModelContract]:
    """Load ``path`` and validate its contract; raises :class:`ModelContractError` naming the
    first problem (prefixed with the file name)."""
    import onnx

    path = Path(path)
    data = path.read_bytes()  # OSError if missing: a usage error, not a contract one
    try:
        model = onnx.load_model_from_string(data)
    except Exception as e:  # noqa: BLE001  (protobuf raises several types on garbage)
        raise ModelContractError(f"{path}: not an ONNX model, or truncated ({type(e).__name__}: "
                                 f"{str(e).splitlines()[0] if str(e) else 'unreadable'})") from None
    if not model.graph.node or not model.opset_import:
        raise ModelContractError(f"{path}: not an ONNX model (no graph or no opset; "
                                 f"{len(data)} bytes)")
    try:  # first: a damaged file is named as one, whatever else its damage breaks
        checksum.verify(data, {p.key: p.value for p in model.metadata_props})
    except ModelContractError as e:
        raise ModelContractError(f"{path}: {e}") from None
    try:
        onnx.checker.check_model(model, full_check=True)
    except (onnx.checker.ValidationError, onnx.shape_inference.InferenceError,
            UnicodeDecodeError) as e:  # the last: a name or string that is not UTF-8
        raise ModelContractError(f"{path}: fails onnx.checker: {str(e).splitlines()[0]}") from None
    opset = {o.domain: o.version for o in model.opset_import}.get("", 0)
    if opset != OPSET:
        raise ModelContractError(f"{path}: opset {opset}, the contract needs {OPSET}")
    try:
        contract = ModelContract.from_metadata({p.key: p.value for p in model.metadata_props})
        contract.check_signature(signature(model.graph.input, model.graph.initializer),
                                 signature(model.graph.output))
        _check_custom_ops(model, contract)
    except ModelContractError as e:
        raise ModelContractError(f"{path}: {e}") from None
    return model, contract


def _check_custom_ops(model: onnx.ModelProto, contract: ModelContract) -> None:
    """The ``custom_ops`` key lists the graph's ``ai.tactile`` nodes as they are (ops, names,
    attributes, in graph order), or is absent when the graph has none."""
    from tactile.export.custom_ops import custom_nodes

    graph = json.loads(json.dumps(custom_nodes(model)))
    if graph != contract.custom_ops:
        def ops(nodes):
            return ", ".join(f"{n['op']} {n.get('name', '')}".strip() for n in nodes) or "none"

        raise ModelContractError(f"metadata key 'custom_ops' lists {ops(contract.custom_ops)} "
                                 f"where the graph has {ops(graph)} (or their attributes differ)")


def signature(values, initializers=()) -> list[tuple[str, str, list]]:
    """(name, elem_type, shape) of graph inputs or outputs, initializers left out."""
    skip = {i.name for i in initializers}
    out = []
    for vi in values:
        if vi.name in skip:
            continue
        t = vi.type.tensor_type
        dims = [d.dim_value if d.HasField("dim_value") else (d.dim_param or None)
                for d in t.shape.dim]
        out.append((vi.name, _TYPES.get(t.elem_type, f"elem_type {t.elem_type}"), dims))
    return out


def describe(path: Path, c: ModelContract, opset: int | None = OPSET,
             kernels: list[str] = ()) -> str:
    """What the file holds, for people (``opset`` None: not checked); ``kernels``: the path
    each custom op takes on this machine (:func:`tactile.runtime.kernels.paths`)."""
    emd = c.preprocessing.get("emd")
    checked = f"opset {opset}, " if opset is not None else ""
    lines = [
        f"{path}: contract ok (format {c.format_version}, {checked}"
        f"{path.stat().st_size / 1e3:.1f} kB, quantization {c.quantization})",
        f"  classes   {', '.join(c.classes)}",
        f"  channels  {', '.join(f'{n} [{u}]' for n, u in zip(c.channels, c.units))}",
        f"  window    {c.window} samples, hop {c.hop}, {c.sample_rate_hz:g} Hz; "
        f"state {c.state_mode}, {c.model} ({_state_text(c)})",
        *_granular_lines(c, emd),
        *_blend_line(c),
        f"  exported  parity {'passed' if c.parity.get('passed') else 'FAILED'} "
        f"(max |dp| {c.parity.get('max_abs_prob_diff')}{_excused(c.parity)})",
        *(f"  codes     {r.get('name')}: {r.get('same_atoms')}/{r.get('rows')} rows the same "
          f"atoms as scikit-learn, max |dc|/|c| {r.get('max_rel_diff')}"
          for r in c.parity.get("codes") or []),
        *_native_parity(c.parity),
        f"  training  {_recorded(c)}",
        f"  file      {_sealed(c)}",
        *_postprocess_lines(c),
        *(f"  kernels   {line}" for line in kernels),
    ]
    return "\n".join(lines)


def _sealed(c: ModelContract) -> str:
    """Whether the file's bytes were checked against its own digest (``describe`` is called on
    files whose digest, where they carry one, has been verified)."""
    if checksum.KEY in c.extra:
        return f"sha256 {c.extra[checksum.KEY][:16]}... verified: the bytes are as exported"
    return ("no sha256 key (exported before files carried one, or removed after an edit): a "
            "damaged copy cannot be told")


def _postprocess_lines(c: ModelContract) -> list[str]:
    """The label stream's defaults and the validation figures they were chosen on, when the
    file carries them; else that it runs raw (an older file, or no setting beat the raw stream
    on validation)."""
    from tactile.postprocess.calibration import summary_line
    from tactile.postprocess.smoothing import figures_from_metadata, settings_from_metadata

    settings = settings_from_metadata(c.extra)
    if settings is None:
        return ["  labels    raw: the file holds no post-processing defaults (tactile-run's "
                "--smooth, --p-min, --hold set them)"]
    figures = figures_from_metadata(c.extra)
    alone = [f"  labels    {settings.describe()} (post-processing defaults)"]
    if not figures:
        return alone
    try:
        line = summary_line(figures)
    except (KeyError, TypeError, ValueError):  # figures of another shape: the setting alone
        return alone
    if figures.get("setting") != settings.describe():  # the keys edited after the calibration
        return [f"{alone[0][:-1]}; the calibration record names another: {line})"]
    return [f"  labels    {line}"]


def _paths(model) -> list[str]:
    """The path each of the file's custom ops takes in ``model``'s session."""
    from tactile.runtime import kernels

    return kernels.paths(model.contract.custom_ops, model.native)


def _native_parity(parity: dict) -> list[str]:
    """The kernels' path's parity, for a file with custom nodes (checked by the exporter on
    both paths; the line above is the portable graphs')."""
    native = parity.get("native")
    if not isinstance(native, dict):
        return []
    return [f"  native    parity {'passed' if native.get('passed') else 'FAILED'} on the kernels "
            f"(max |dp| {native.get('max_abs_prob_diff')}{_excused(native)})"]


def _excused(parity: dict) -> str:
    """The windows a coder model's parity excused, if any: for near-tie atom flips and for
    float32 code accuracy (files written before that kind have no count of it)."""
    out = ""
    n, m = parity.get("windows_excused"), parity.get("windows_excused_float32")
    if n:
        out += (f"; {n} of {parity.get('windows')} windows excused for near-tie atom flips, "
                f"max |dp| {parity.get('max_abs_prob_diff_excused')}")
    if m:
        out += (f"; {m} of {parity.get('windows')} for float32 code accuracy, "
                f"max |dp| {parity.get('max_abs_prob_diff_excused_float32')}")
    return out


def _granular_lines(c: ModelContract, emd) -> list[str]:
    """The pen's EMD line, or a granular model's modalities, after the high-rate signals the
    model reads at their own rate (either kind)."""
    lines = [f"  signal    {s.name}: {len(s.channels)} sub-samples per frame ({s.channels[0]}"
             f"..{s.channels[-1]}), {s.rate_hz:g} Hz" for s in c.signals]
    if not c.modalities:
        return [f"  emd       {_emd_text(emd)}", *lines]
    for m in c.modalities:
        units = len(m.channels) // max(1, round(m.rate_hz / c.sample_rate_hz))
        emd_text = f"{m.imfs} IMFs x {c.preprocessing.get('sifts')} sifts" if m.imfs else "no EMD"
        codes = f", {m.atoms} atoms, {m.nonzero} non-zeros" if m.atoms else ""
        lines.append(f"  modality  {m.name}: {units} {'signal' if m.signal else 'channel'}"
                     f"{'s' if units != 1 else ''} at {m.rate_hz:g} Hz, {emd_text}, "
                     f"{m.steps} steps{codes}")
    return lines


def _blend_line(c: ModelContract) -> list[str]:
    """What the blended regression reads and weighs (a file exported before it was recorded,
    or a model without one: no line)."""
    b = c.training_metrics.get("blend")
    if not isinstance(b, dict) or "mix" not in b:
        return []
    if not b["mix"]:
        return ["  blend     mix 0: the recurrent model alone (the regression left out)"]
    n = len(c.channels)
    c_text = f"{b['c']:g}" if isinstance(b.get("c"), (int, float)) else "?"
    return [f"  blend     {b['mix']:g} x a logistic regression (C {c_text}) on "
            f"whole-window features: {n} channel{'s' * (n != 1)} each by itself "
            f"(mean, log std, 5 band energies)"]


def _emd_text(emd) -> str:
    """The pen's EMD setting for people: ``accel_z: 4 IMFs x 10 sifts`` (or as recorded)."""
    if emd is None:
        return "none"
    try:
        return f"{', '.join(emd['channels'])}: {emd['imfs']} IMFs x {emd['sifts']} sifts"
    except (KeyError, TypeError):
        return str(emd)


def _fmt(value) -> str:
    """A recorded figure for people: four decimals if it is a number."""
    return f"{value:.4f}" if isinstance(value, float) else str(value)


def _state_text(c: ModelContract) -> str:
    """``layers x hidden``, or for an ensemble (its training config says how many members)
    ``N members x (layers x hidden)``; an F-RNN's state says it is one LSTM's per modality."""
    try:
        members = int(json.loads(c.extra.get("training_config", "{}")).get("ensemble", 1))
    except (ValueError, TypeError, AttributeError):
        members = 1
    if members > 1 and c.state_layers % members == 0:
        return f"{members} members x ({c.state_layers // members} x {c.state_hidden})"
    n = len(c.modalities)
    if c.model == "f_rnn" and n > 1 and c.state_hidden % n == 0:  # an LSTM per modality
        return (f"{c.state_layers} x {c.state_hidden}: {n} modalities' LSTMs of "
                f"{c.state_layers} x {c.state_hidden // n}")
    return f"{c.state_layers} x {c.state_hidden}"


def _recorded(c: ModelContract) -> str:
    """The accuracy training measured, with what it was measured on."""
    m = c.training_metrics
    acc = m.get("accuracy")
    if not isinstance(acc, (int, float)) or isinstance(acc, bool):
        return "none: the file's training_metrics holds no test accuracy"
    if not 0 <= acc <= 1:  # NaN too: a hand-edited or damaged file
        return f"none: the file's training_metrics holds accuracy {acc!r}, not in [0, 1]"
    windows = m.get("windows")
    on = f"{windows} windows of the run's test split" if isinstance(windows, int) else (
        "the run's test split")
    return f"accuracy {_fmt(m.get('accuracy'))} on {on} (measured at training, in PyTorch)"


def _reparity(path: Path, c: ModelContract, run_dir: Path, data: Path | None,
              windows: int, native: bool) -> bool:
    """Parity of the file against the run's PyTorch model, on the portable graph and, with
    ``native`` (the kernels run the file's custom nodes here, as in ``tactile-run``), also on
    the kernels, as the exporter checks them; both must pass."""
    from tactile.export.parity import compare, compare_on_kernels
    from tactile.export.windows import probe_windows
    from tactile.training.checkpoint import load_checkpoint
    from tactile.training.config import TrainConfig

    model, ck = load_checkpoint(run_dir)
    for key, mine in (("classes", c.classes), ("channels", c.channels)):
        if tuple(ck[key]) != mine:
            raise ModelContractError(f"{path} and {run_dir} differ in {key}: {list(mine)} vs "
                                     f"{list(ck[key])}")
    if ck["config"]["window"] != c.window or ck["config"]["state"] != c.state_mode:
        raise ModelContractError(f"{path} and {run_dir} differ in window or state mode")
    kind = ck["config"].get("model", TrainConfig.model)  # its default when a config omits it
    if kind != c.model:
        raise ModelContractError(f"{path} and {run_dir} differ in model: {c.model} vs {kind} "
                                 "(is --run the run this file was exported from?)")
    crit = "strict" if c.quantization == "none" else "int8"
    probe = probe_windows(ck, data, windows)
    p = compare(model, str(path), probe, ck, criterion=crit)
    if not native:  # a file with custom nodes names the path it checked, as the export does
        print(("portable graph:\n" if c.custom_ops else "") + p.table())
        return p.passed
    print("portable graph:\n" + p.table())
    q = compare_on_kernels(model, str(path), probe, ck, crit)
    print("native kernels:\n" + q.table())
    return p.passed and q.passed


def _accuracy(loaded, c: ModelContract, data: Path) -> None:
    """The file's accuracy on ``data`` (its run's test split when the data holds those takes),
    run by ``loaded`` (:class:`~tactile.runtime.model.Model`: the path ``tactile-run`` takes)."""
    from tactile.export.windows import from_dataset

    ck = {"classes": list(c.classes), "channels": list(c.channels), "units": list(c.units),
          "sample_rate_hz": c.sample_rate_hz, "config": {"window": c.window, "hop": c.hop},
          "seen_fingerprints": c.training_metrics.get("seen_fingerprints")}
    takes = c.training_metrics.get("test_takes")
    if isinstance(takes, dict):  # the run's test split, recorded at export (read defensively)
        ck["test_rows"] = {n: v.get("rows") for n, v in takes.items() if isinstance(v, dict)}
        ck["test_fingerprints"] = {n: v.get("fingerprint") for n, v in takes.items()
                                   if isinstance(v, dict)}
    # a file names the signals its model reads in time order (none read as plain channels)
    probe = from_dataset(ck, data, tuple((s.name, s.channels) for s in c.signals))
    sess = loaded.session
    labels = np.empty(len(probe), np.int64)
    zero = np.zeros((c.state_layers, 1, c.state_hidden), np.float32)
    for rows in probe.runs:  # each gap-free run in order, following the state mode
        h, cc = zero, zero
        for r in rows:
            p, h2, c2 = sess.run(None, {"x": probe.x[r : r + 1], "h": h, "c": cc})
            labels[r] = p.argmax(1)[0]
            if c.state_mode == "carry":
                h, cc = h2, c2
    acc = float((labels == probe.y).mean())
    same = probe.source.startswith("the run's test split")
    print(f"measured on      {probe.source}: {len(probe)} windows")
    on = ("" if not c.custom_ops else
          ", on the native kernels" if loaded.native else ", on the portable graph")
    print(f"accuracy         {acc:.4f} (this file in onnxruntime, one window at a time{on})")
    print(f"recorded         {_recorded(c)}"
          + ("" if same else "; other windows than these, so not comparable"))


def board_check(path: Path) -> None:
    """The check with onnxruntime only: what ``tactile-run`` loads, validates and runs."""
    from tactile.runtime.model import Model

    model = Model(path)  # contract, signature and outputs, as tactile-run checks them (exit 3)
    model.probe(2)  # and the batch axis really dynamic
    c = model.contract
    h, cc = model.zero_state()
    probs, _, _ = model.classify(np.zeros((1, c.window, len(c.channels)), np.float32), h, cc)
    if probs.shape != (1, len(c.classes)) or not (np.isfinite(probs).all()
                                                  and abs(float(probs.sum()) - 1.0) < 1e-3):
        raise ModelContractError(f"{path}: a zero window gives probabilities {probs.tolist()}, "
                                 f"not {len(c.classes)} finite values summing to 1")
    print(describe(path, c, opset=None, kernels=_paths(model)))
    print("  checked   with onnxruntime only (the [train] extra is not installed): the contract, "
          "the graph's signature, one window; the extra adds onnx.checker and the opset check")


def check_file(path: Path, run_dir: Path | None = None, data: Path | None = None,
               windows: int = 256) -> None:
    """Check model file ``path`` and print what it holds: its contract (with the ``[train]``
    extra: :func:`load_contract` and a run at batch 1 and 2; without it: :func:`board_check`),
    then with ``run_dir`` parity against that run's model on at most ``windows`` windows (of
    ``data`` if given), or with ``data`` alone the file's accuracy on it. Raises
    :class:`ModelContractError` (a broken file, failed parity) or :class:`ConfigError` (a run
    or data without the extra)."""
    model_file(path)  # missing or a folder: the line and exit code tactile-run gives
    try:
        with holding_signals():  # (a Ctrl-C that cuts an import short: the command's line)
            import onnx  # noqa: F401
            import torch
    except ModuleNotFoundError:  # a board: no onnx, no torch (the [train] extra)
        if run_dir is not None or data is not None:
            raise ConfigError("--run and --data need the [train] extra: "
                              "pip install 'tactile-pen[train]'") from None
        board_check(path)
        return
    torch.set_num_threads(1)  # one core's figures; also avoids contention on a small board
    _, contract = load_contract(path)
    with holding_signals():
        from tactile.runtime.model import Model

    loaded = Model(path)
    loaded.probe(2)  # outputs of the declared shapes at batch 1 (as tactile-run
    # checks at load) and 2 (the batch axis really dynamic)
    print(describe(path, contract, kernels=_paths(loaded)))
    if run_dir is not None:
        if not _reparity(path, contract, run_dir, data, windows,
                         native=bool(contract.custom_ops) and loaded.native):
            source = contract.extra.get("source_run")
            here = Path(run_dir).resolve().name  # as the exporter names it (--run . too)
            other = (f"; the file says it was exported from a run named {source!r}, not "
                     f"{here!r}" if source and source != here else "")
            raise ModelContractError(f"{path}: parity against {run_dir} failed "
                                     f"(table above){other}")
    elif data is not None:
        _accuracy(loaded, contract, data)


__all__ = ["load_contract", "signature", "describe", "board_check", "check_file"]
