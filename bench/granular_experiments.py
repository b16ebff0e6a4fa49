"""The granular-media paper's Table 1 on the BioTac recordings and the simulated pen.

    python bench/granular_experiments.py                          # everything, 3 seeds
    python bench/granular_experiments.py --dataset biotac --block vibration --models sf_rnn
    python bench/granular_experiments.py --seeds 1 --set epochs=5 # a quick look
    python bench/granular_experiments.py --budget cut             # the earlier cut budget
    python bench/granular_experiments.py --report                 # print what the cache holds

Per dataset and block (BioTac: vibration only, all three modalities; the pen: pressure,
acceleration and rotation), per model (linear, sparse linear, F-RNN, SF-RNN) and per seed:
``tactile-train DATA --config configs/granular/<row>.toml --set seed=S``, then
``tactile-export`` of the run, then the exported file's time to label 1 s of data (one
onnxruntime thread, the model's streaming hop, EMD and coding included). Prints the paper's
Table 1 layout with the mean and spread over seeds and the paper's figures beside ours.

The data and the runs live in ``--cache`` (outside the repository): the BioTac takes are
imported once with ``tactile-import-biotac``, the pen set simulated once with ``tactile-sim``;
a finished step (training, export, timing) is never redone, so an interrupted benchmark
continues where it stopped (a training stopped by Ctrl-C resumes from its last epoch). Runs
are kept per configuration: editing a config file or ``--set`` starts new runs. Every run uses
one torch thread (``--threads``); run it under ``nice`` on a shared machine. Several processes
may share one cache (e.g. one per dataset, or the same command twice): each run is locked by
the process training it, and the others pass it by.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import importlib.util
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
CONFIGS = REPO / "configs" / "granular"
BIOTAC = REPO.parent / "shared" / "datasets" / "biotac-bolt"
CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "tactile" / "granular"

MODELS = ("linear", "sparse_linear", "f_rnn", "sf_rnn")
LABELS = {"linear": "linear", "sparse_linear": "sparse linear", "f_rnn": "F-RNN",
          "sf_rnn": "SF-RNN"}
BLOCKS = {"biotac": ("vibration", "all"), "pen": ("all",)}
TITLES = {("biotac", "vibration"): "BioTac, vibration only",
          ("biotac", "all"): "BioTac, all three modalities (vibration, pressure, electrodes)",
          ("pen", "all"): "simulated pen, all three modalities (pressure, acceleration, "
                          "rotation)"}
BUDGETS = {
    "full": (),  # the configs as they are: the toolkit's training defaults
    # the earlier budget-cut table: at most 20 epochs, patience 5, early stopping on the
    # validation loss, no refit, 4 sifts per IMF
    "cut": ("epochs=20", "patience=5", "select=loss", "refit=off", "emd_sifts=4"),
}
PEN_TEXTURES = ("non_contact", "paper", "nonwoven_cloth", "plastic_folder", "mouse_pad")

# The paper's Table 1 (granular media, two classes): dims of the feature space, neurons,
# time to label 1 s of data (ms), validation / test / novel accuracy (%).
PAPER = {
    "vibration": {"linear": (8, None, 1.9, 49.5, 49.1, 49.3),
                  "sparse_linear": (200, None, 2.4, 67.0, 72.0, 50.7),
                  "f_rnn": (200, 50, 0.4, 63.5, 79.9, 61.4),
                  "sf_rnn": (200, 50, 2.6, 95.9, 95.7, 94.8)},
    "all": {"linear": (32, None, 2.2, 60.8, 62.0, 62.0),
            "sparse_linear": (400, None, 2.7, 99.7, 99.7, 85.3),
            "f_rnn": (400, 50, 0.6, 90.5, 84.1, 79.4),
            "sf_rnn": (400, 50, 3.0, 98.4, 98.7, 98.0)},
}


@dataclass(frozen=True)
class Row:
    """One line of a table: a dataset, a block (which modalities) and a model."""

    dataset: str
    block: str
    model: str

    @property
    def name(self) -> str:
        """The config file's stem: ``biotac-vibration-sf_rnn``, ``pen-linear``."""
        if self.dataset == "pen":
            return f"pen-{self.model}"
        return f"{self.dataset}-{self.block}-{self.model}"

    def config(self, folder: Path = CONFIGS) -> Path:
        return folder / f"{self.name}.toml"


def rows(datasets: Iterable[str], blocks: Iterable[str] | None,
         models: Iterable[str]) -> list[Row]:
    """Every (dataset, block, model) asked for, in table order; blocks a dataset lacks are
    left out (the pen has only ``all``)."""
    out = []
    for d in datasets:
        for b in BLOCKS[d]:
            if blocks is None or b in blocks:
                out += [Row(d, b, m) for m in MODELS if m in models]
    return out


# --- commands ------------------------------------------------------------------------------

def command(name: str) -> list[str]:
    """The toolkit's command ``name`` as installed beside this Python (the same environment)."""
    here = Path(sys.executable).with_name(name)
    found = str(here) if here.exists() else shutil.which(name)
    if found is None:
        raise SystemExit(f"granular_experiments: {name} not found: install the project "
                         "(pip install -e '.[train,biotac]')")
    return [found]


def call(argv: Sequence[str], log: Path) -> float:
    """Run a command, its stdout and stderr appended to ``log``; returns its CPU time (user +
    sys, s, with its children). A failure ends the benchmark with the log's last lines."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as f:
        f.write(f"$ {' '.join(argv)}\n")
        f.flush()
        proc = subprocess.Popen(list(argv), stdout=f, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        tail = "".join(log.read_text().splitlines(True)[-5:])
        raise RuntimeError(f"{' '.join(argv[:2])}... exited with {proc.returncode}:\n{tail}")
    return usage.ru_utime + usage.ru_stime


# --- data ----------------------------------------------------------------------------------

def _ready(folder: Path, make) -> Path:
    """``folder`` made once by ``make(tmp)``: written to a temporary sibling, then renamed,
    so that an interrupted import is never taken for a finished one."""
    if folder.exists():
        return folder
    tmp = folder.with_name(folder.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.parent.mkdir(parents=True, exist_ok=True)
    make(tmp)
    tmp.rename(folder)
    return folder


def biotac_data(cache: Path, source: Path = BIOTAC) -> Path:
    """The BioTac BOLT trials as takes (``tactile-import-biotac``), imported once."""
    files = sorted(source.glob("*.h5"))
    if not files:
        raise SystemExit(f"granular_experiments: no .h5 files in {source} (--biotac)")
    return _ready(cache / "data" / "biotac", lambda tmp: call(
        [*command("tactile-import-biotac"), *map(str, files), "--out", str(tmp)],
        cache / "data" / "biotac.log"))


def pen_data(cache: Path, users: int, seconds: float) -> Path:
    """The simulated pen set (``tactile-sim --dataset``): ``users`` users x the pen paper's
    experiment-2 textures x ``seconds``, made once per size."""
    name = f"pen-{users}x{seconds:g}s"
    return _ready(cache / "data" / name, lambda tmp: call(
        [*command("tactile-sim"), "--dataset", str(tmp), "--takes", str(users),
         "--seconds", f"{seconds:g}", "--textures", ",".join(PEN_TEXTURES), "--seed", "1"],
        cache / "data" / f"{name}.log"))


# --- runs ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Job:
    row: Row
    seed: int
    config: Path
    data: Path
    folder: Path  # the run folder
    sets: tuple[str, ...]  # --set KEY=VALUE beyond seed and threads

    def settings(self, threads: int):
        """The run's TrainConfig: the config file, ``--set``, the seed and the threads (what
        ``tactile-train DATA --config FILE --set seed=S --set threads=T`` trains)."""
        from tactile.training.config import TrainConfig
        from tactile.training.overrides import parse_sets

        return parse_sets([*self.sets, f"seed={self.seed}", f"threads={threads}"],
                          TrainConfig.from_toml(self.config))


def settings_key(config: Path, sets: Sequence[str], data: Path) -> str:
    """8 hex digits naming a configuration: the config file's text, the ``--set`` overrides
    and the dataset, so that changed settings never reuse an old run."""
    h = hashlib.sha256(config.read_bytes())
    h.update(json.dumps([list(sets), data.name]).encode())
    return h.hexdigest()[:8]


def jobs_for(rows_: Sequence[Row], seeds: Sequence[int], data: dict[str, Path], cache: Path,
             sets: Sequence[str], configs: Path = CONFIGS) -> list[Job]:
    out = []
    for row in rows_:
        cfg = row.config(configs)
        if not cfg.exists():
            raise SystemExit(f"granular_experiments: {cfg} missing")
        key = settings_key(cfg, sets, data[row.dataset])
        for s in seeds:
            out.append(Job(row, s, cfg, data[row.dataset],
                           cache / "runs" / row.name / key / f"seed{s}", tuple(sets)))
    return out


def finished(folder: Path) -> dict | None:
    """The run's metrics when its training finished (not interrupted), else None."""
    try:
        m = json.loads((folder / "metrics.json").read_text())
    except (OSError, ValueError):
        return None
    return None if m.get("interrupted") or (folder / "resume.pt").exists() else m


def _cpu() -> float:
    """CPU time (user + sys) of this process so far, s."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


class EMDMemo:
    """EMD results kept on disk by the content of their input, for this benchmark only.

    Every run of a dataset normalises with the same training split (named by the configs'
    ``test``/``val``), so every model and seed decomposes the very same windows; the EMD is
    deterministic, so a result read back is the one it would compute. ``install`` wraps
    ``EMD.forward`` in this process: an input seen before (same bytes, shape, dtype, IMFs and
    sifts) is read from ``folder``, otherwise computed and stored (written to a temporary
    name, then renamed: two benchmark processes may share the folder)."""

    def __init__(self, folder: Path) -> None:
        self.folder, self.hits, self.misses = folder, 0, 0

    def install(self) -> None:
        import torch

        from tactile.training.emd import EMD

        if getattr(EMD.forward, "memo", None) is self:
            return
        compute = getattr(EMD.forward, "compute", EMD.forward)
        memo = self

        def forward(module, x):
            if x.requires_grad:
                return compute(module, x)
            h = hashlib.sha256(x.detach().contiguous().cpu().numpy().tobytes())
            h.update(repr((tuple(x.shape), str(x.dtype), module.n_imfs, module.n_sifts)).encode())
            path = memo.folder / f"{h.hexdigest()[:32]}.pt"
            if path.exists():
                memo.hits += 1
                return tuple(torch.load(path, weights_only=True))
            memo.misses += 1
            out = compute(module, x)
            memo.folder.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{os.getpid()}.tmp")
            torch.save(list(out), tmp)
            tmp.replace(path)
            return out

        forward.memo, forward.compute = self, compute
        EMD.forward = forward


class Busy(Exception):
    """Another live benchmark process is working on this run."""


class RunLock:
    """``RUN/.lock`` holding the pid of the process working on the run, so that several
    benchmark processes can share one cache (each takes the runs no other one holds). A lock
    whose process is gone is taken over."""

    def __init__(self, folder: Path) -> None:
        self.path = folder / ".lock"

    def __enter__(self) -> RunLock:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            except FileExistsError:
                try:
                    os.kill(int(self.path.read_text() or "0"), 0)
                except (ProcessLookupError, ValueError):  # stale: its process is gone
                    self.path.unlink(missing_ok=True)
                    continue
                except PermissionError:
                    pass
                raise Busy(str(self.path.parent)) from None
            os.write(fd, str(os.getpid()).encode())
            os.close(fd)
            return self
        raise Busy(str(self.path.parent))

    def __exit__(self, *exc) -> None:
        self.path.unlink(missing_ok=True)


def train_job(job: Job, threads: int, say=print) -> None:
    """Train (or resume, after Ctrl-C) and export one run; a finished step is skipped. Raises
    :class:`Busy` when another process holds the run."""
    with RunLock(job.folder):
        _train_job(job, threads, say)


def _train_job(job: Job, threads: int, say=print) -> None:
    from tactile.training.checkpoint import load_resume
    from tactile.training.config import TrainConfig
    from tactile.training.train import train

    log = job.folder / "bench.log"
    if finished(job.folder) is None:
        t0, c0 = time.perf_counter(), _cpu()
        if (job.folder / "resume.pt").exists():
            r = load_resume(job.folder)
            m = train(job.data, job.folder, TrainConfig.from_dict(r["config"]), progress=False,
                      resume=r["state"])
        else:
            m = train(job.data, job.folder, job.settings(threads), progress=False)
        if m.get("interrupted"):
            raise KeyboardInterrupt
        cost = {"wall_seconds": round(time.perf_counter() - t0, 1),
                "cpu_seconds": round(_cpu() - c0, 1)}
        (job.folder / "cost.json").write_text(json.dumps(cost) + "\n")
        say(f"<!-- {job.row.name} seed {job.seed}: val {m['val_accuracy']:.3f} test "
            f"{m['accuracy']:.3f} novel "
            f"{(m.get('shifted') or {}).get('mean', float('nan')):.3f}, best epoch "
            f"{m['best_epoch'] + 1} of {m['epochs_run']}, {cost['cpu_seconds']} s CPU "
            f"({cost['wall_seconds']} s wall) -->", flush=True)
    onnx, failed = job.folder / "model.onnx", job.folder / "export-failed.txt"
    if not onnx.exists() and not failed.exists():
        try:
            call([*command("tactile-export"), str(job.folder), "-o", str(onnx),
                  "--data", str(job.data)], log)
        except RuntimeError as e:  # e.g. parity refused: the run's figures still stand
            failed.write_text(f"{e}\n")
            say(f"<!-- {job.row.name} seed {job.seed}: export failed: "
                f"{str(e).splitlines()[-1]} -->", flush=True)


def time_job(job: Job, seconds: float = 5.0) -> dict:
    """The exported file's time to label 1 s of data, measured once and kept: the export's
    :func:`label_time` (``bench/label_time.py``: one onnxruntime thread, batch 1 at the
    contract's hop, EMD and coding in the graph) on ``seconds`` of consecutive windows of the
    run's first test take."""
    path = job.folder / "timing.json"
    if path.exists():
        return json.loads(path.read_text())
    t = _label_time()(job.folder / "model.onnx", windows=test_windows(job, seconds))
    t = {k: v for k, v in t.items() if isinstance(v, (int, float, str))}
    path.write_text(json.dumps(t) + "\n")
    return t


def _label_time():
    spec = importlib.util.spec_from_file_location("label_time", REPO / "bench" / "label_time.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.label_time


def test_windows(job: Job, seconds: float) -> np.ndarray:
    """(N, window, C) float32: consecutive windows at the run's hop from its first test take,
    ``seconds`` of data, in the contract's channels (recycled if the take is shorter)."""
    import torch

    from tactile.device.recordings import read_take

    ck = torch.load(job.folder / "checkpoint.pt", map_location="cpu", weights_only=True)
    take = read_take(job.data / sorted(ck["test_rows"])[0])
    cfg = ck["config"]
    v = take.values()[:, [take.channels.index(c) for c in ck["channels"]]].astype(np.float32)
    n = max(1, round(seconds * take.info.sample_rate_hz / cfg["hop"]))
    starts = np.arange(0, len(v) - cfg["window"] + 1, cfg["hop"])
    starts = starts[np.arange(n) % len(starts)]
    return v[starts[:, None] + np.arange(cfg["window"])[None, :]]


# --- what a run is: its size, its figures --------------------------------------------------

def shape_of(folder: Path) -> tuple[int, int | None]:
    """(dims of the feature space the classifier sees, neurons per recurrent layer or None):
    the Table's two size columns. Codes: the atoms of every modality; F-RNN: the images'
    features; linear: its inputs."""
    from tactile.training.checkpoint import load_checkpoint

    model, ck = load_checkpoint(folder)
    cfg = model.cfg
    rnn = cfg.model in ("sf_rnn", "f_rnn", "lstm")
    if cfg.modalities:
        return model.pre.n_features, cfg.hidden if rnn else None
    return model.head.out.in_features, cfg.hidden if rnn else None


@dataclass
class Figures:
    """One row's figures over its finished seeds (accuracies as fractions)."""

    seeds: list[int]
    dims: int | None
    neurons: int | None
    ms: list[float]
    val: list[float]
    test: list[float]
    novel: list[float]
    cpu: list[float]
    epochs: list[str]
    export_failed: list[int] = dataclasses.field(default_factory=list)


def collect(jobs: Sequence[Job], timing: bool = True) -> dict[Row, Figures]:
    out: dict[Row, Figures] = {}
    for job in jobs:
        f = out.setdefault(job.row, Figures([], None, None, [], [], [], [], [], []))
        m = finished(job.folder)
        if m is None:
            continue
        f.seeds.append(job.seed)
        f.dims, f.neurons = shape_of(job.folder)
        f.val.append(m["val_accuracy"])
        f.test.append(m["accuracy"])
        f.novel.append((m.get("shifted") or {}).get("mean", float("nan")))
        f.epochs.append(f"{m['best_epoch'] + 1}/{m['epochs_run']}")
        cost = job.folder / "cost.json"
        if cost.exists():
            f.cpu.append(json.loads(cost.read_text()).get("cpu_seconds", float("nan")))
        if timing and (job.folder / "model.onnx").exists():
            f.ms.append(time_job(job)["ms_per_s"])
        elif (job.folder / "export-failed.txt").exists():
            f.export_failed.append(job.seed)
    return out


def spread(values: Sequence[float], scale: float = 100.0, digits: int = 1) -> str:
    """``mean +/- sd`` (population sd over seeds) of ``values`` x ``scale``; ``-`` if none."""
    v = np.array([x for x in values if x == x], dtype=float) * scale
    if not len(v):
        return "-"
    if len(v) == 1:
        return f"{v[0]:.{digits}f}"
    return f"{v.mean():.{digits}f} +/- {v.std():.{digits}f}"


def table(dataset: str, block: str, figs: dict[Row, Figures]) -> str:
    """The paper's Table 1 layout for one dataset and block, the paper's figures beside."""
    paper = PAPER[block]
    lines = [f"#### {TITLES[(dataset, block)]}", "",
             "| model | feature dims | neurons | time to label 1 s (ms) | validation (%) | "
             "test (%) | novel, +/-0.2 s (%) | test - novel | seeds | paper: dims, neurons, "
             "ms, validation / test / novel |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for row, f in figs.items():
        if (row.dataset, row.block) != (dataset, block):
            continue
        p = paper[row.model]
        drop = [t - n for t, n in zip(f.test, f.novel, strict=True)]
        failed = (f" (export failed: seed {', '.join(map(str, f.export_failed))})"
                  if f.export_failed else "")
        size = ("-", "-") if not f.seeds else (
            str(f.dims), "N/A" if f.neurons is None else str(f.neurons))
        cells = [LABELS[row.model], *size,
                 spread(f.ms, 1.0, 2) + failed, spread(f.val), spread(f.test), spread(f.novel),
                 spread(drop), ", ".join(map(str, f.seeds)) or "none finished",
                 f"{p[0]}, {'N/A' if p[1] is None else p[1]}, {p[2]}, "
                 f"{p[3]} / {p[4]} / {p[5]}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def details(figs: dict[Row, Figures]) -> str:
    """Per-row seeds' figures as HTML comments (what the table averages)."""
    out = []
    for row, f in figs.items():
        if not f.seeds:
            continue
        out.append(f"<!-- {row.name}: seeds {f.seeds}; test {[round(t, 3) for t in f.test]}; "
                   f"novel {[round(n, 3) for n in f.novel]}; best epoch/epochs {f.epochs}; "
                   f"CPU s per run {f.cpu} -->")
    return "\n".join(out)


# --- command line --------------------------------------------------------------------------

def _seeds(text: str) -> tuple[int, ...]:
    """``3`` (seeds 0, 1, 2) or a list ``0,4,7``."""
    try:
        if "," not in text:
            n = int(text)
            if n < 1:
                raise ValueError
            return tuple(range(n))
        seeds = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: a count (3) or seeds (0,1,2)") from None
    if not seeds:
        raise argparse.ArgumentTypeError("give at least one seed")
    return seeds


def _choices(allowed: Sequence[str]):
    def parse(text: str) -> tuple[str, ...]:
        got = tuple(v.strip() for v in text.split(",") if v.strip())
        bad = [v for v in got if v not in allowed]
        if bad or not got:
            raise argparse.ArgumentTypeError(f"{text!r}: choose from {', '.join(allowed)}")
        return got
    return parse


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cache", type=Path, default=CACHE,
                   help=f"data and runs (default {CACHE}); outside the repository")
    p.add_argument("--dataset", type=_choices(tuple(BLOCKS)), default=tuple(BLOCKS),
                   help="comma-separated: biotac, pen (default both)")
    p.add_argument("--block", type=_choices(("vibration", "all")),
                   help="comma-separated: vibration, all (default every block)")
    p.add_argument("--models", type=_choices(MODELS), default=MODELS,
                   help=f"comma-separated subset of {', '.join(MODELS)}")
    p.add_argument("--seeds", type=_seeds, default=(0, 1, 2),
                   help="a count (3: seeds 0, 1, 2, the default) or a list 0,1,2")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="tactile-train --set for every run (new runs: part of the run's key)")
    p.add_argument("--budget", choices=tuple(BUDGETS), default="full",
                   help="full: the configs' training settings, the toolkit's defaults "
                        "(default); cut: + " + " ".join(f"--set {v}" for v in BUDGETS["cut"]))
    p.add_argument("--threads", type=int, default=1, help="torch threads per run (default 1)")
    p.add_argument("--no-memo", action="store_true",
                   help="compute every EMD (default: reuse identical ones, see EMDMemo)")
    p.add_argument("--biotac", type=Path, default=BIOTAC, help="folder of the BOLT .h5 files")
    p.add_argument("--pen-users", type=int, default=15,
                   help="simulated users per texture (default 15: 9 train, 3 validate, 3 test)")
    p.add_argument("--pen-seconds", type=float, default=60.0, help="seconds per take")
    p.add_argument("--configs", type=Path, default=CONFIGS, help=argparse.SUPPRESS)
    p.add_argument("--report", action="store_true",
                   help="train nothing: print the tables of the runs the cache holds")
    p.add_argument("--no-timing", action="store_true", help="leave out the time to label 1 s")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    todo = rows(args.dataset, args.block, args.models)
    if not todo:
        raise SystemExit("granular_experiments: no row matches --dataset/--block/--models")
    data = {}
    if "biotac" in args.dataset:
        data["biotac"] = biotac_data(args.cache, args.biotac)
    if "pen" in args.dataset:
        data["pen"] = pen_data(args.cache, args.pen_users, args.pen_seconds)
    sets = [*BUDGETS[args.budget], *args.set]
    jobs = jobs_for(todo, args.seeds, data, args.cache, sets, args.configs)
    if not args.report:
        from tactile.training.run_files import libraries_line

        print(libraries_line(), flush=True)
        # seed-major: every row gets its first seed before any row gets its second
        order = sorted(jobs, key=lambda j: (args.seeds.index(j.seed), todo.index(j.row)))
        memo = EMDMemo(args.cache / "emd")
        if not args.no_memo:
            memo.install()
        try:
            for j in order:
                try:
                    train_job(j, args.threads)
                except Busy:
                    print(f"<!-- {j.row.name} seed {j.seed}: another process holds it -->",
                          flush=True)
        except KeyboardInterrupt:  # a training stopped by Ctrl-C saved its last epoch
            print("granular_experiments: stopped; the same command continues where it stopped",
                  file=sys.stderr)
            return 130
        finally:  # also when stopped: what the memo saved so far
            if not args.no_memo:
                print(f"<!-- EMD memo: {memo.hits} batches reused, {memo.misses} computed -->",
                      flush=True)
    figs = collect(jobs, timing=not args.no_timing)
    for dataset in args.dataset:
        for block in BLOCKS[dataset]:
            if any((r.dataset, r.block) == (dataset, block) for r in todo):
                print("\n" + table(dataset, block, figs) + "\n", flush=True)
    print(details(figs))
    return 0


if __name__ == "__main__":
    sys.exit(main())
