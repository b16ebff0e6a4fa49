"""Packaging rules: the runtime is torch-free; the base requirements are the runtime's only."""

from __future__ import annotations

import subprocess
import sys
import tomllib

from conftest import REPO


def test_runtime_and_device_import_without_torch():
    code = (
        "import sys, tactile.runtime, tactile.runtime.runner, tactile.runtime.model, "
        "tactile.runtime.stream, tactile.contract, tactile.device, "
        "tactile.device.protocol.decoder, tactile.device.recordings.recorder, "
        "tactile.device.sim.simlink, tactile.device.link.portlist, "
        "tactile.runtime.live, tactile.runtime.monitor, tactile.runtime.pen, "
        "tactile.runtime.commands.run, tactile.runtime.commands.monitor\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'onnx', 'PyEMD'))\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"torch-side modules imported: {out.stdout}"


def test_python_started_in_the_clones_root_imports_the_whole_package():
    """Python started in a clone's root finds its tactile/ folder first; an installed copy
    (not this editable one) would not serve the stages' folders beside it: the clone's
    tactile/ takes them in, so that `python -c "import tactile.runtime"` works there."""
    import sysconfig

    # -S: no .pth files, so no editable install's finder; the venv's packages by hand
    packages = sysconfig.get_paths()["purelib"]
    code = (f"import sys; sys.path.insert(0, ''); sys.path.append({packages!r})\n"
            "import tactile.runtime.stream, tactile.device.protocol, tactile.postprocess\n"
            "print(tactile.runtime.stream.__file__)\n")
    out = subprocess.run([sys.executable, "-S", "-c", code], capture_output=True, text=True,
                         cwd=REPO)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == str(REPO / "runtime" / "stream.py")


def test_base_requirements_are_the_runtime_only():
    meta = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    names = {r.split(">")[0].split("=")[0].split("!")[0].split("<")[0].strip()
             for r in meta["dependencies"]}
    assert names == {"numpy", "onnxruntime", "pyserial"}
    assert any(r.startswith("torch>=") for r in meta["optional-dependencies"]["train"])
    # the aarch64 wheel of onnxruntime 1.21.0 crashes on a Raspberry Pi 4
    assert any("!=1.21.0" in r for r in meta["dependencies"] if r.startswith("onnxruntime"))


def test_the_built_wheel_requires_no_torch(tmp_path):
    """What `pip install tactile-pen` (no extras) asks for, read from the wheel pip would get."""
    import shutil
    import zipfile

    # built from a copy: setuptools writes build/ and an .egg-info beside the sources it builds
    src = tmp_path / "src"
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(
        ".*", "__pycache__", "build", "dist", "*.egg-info", "data", "runs", "tests", "bench"))
    before = sorted(p.name for p in REPO.iterdir())
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
         "-w", str(tmp_path), str(src)],
        check=True, capture_output=True,
    )
    assert sorted(p.name for p in REPO.iterdir()) == before  # nothing new in the checkout
    (wheel,) = tmp_path.glob("tactile_pen-*.whl")
    with zipfile.ZipFile(wheel) as z:
        meta = next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))
        lines = z.read(meta).decode().splitlines()
        names = z.namelist()
    base = [ln for ln in lines if ln.startswith("Requires-Dist:") and "extra ==" not in ln]
    base_names = {ln.split(":", 1)[1].strip().split()[0].split(">")[0].split("!")[0]
                  for ln in base}
    assert base_names == {"numpy", "onnxruntime", "pyserial"}, base
    extras = [ln for ln in lines if ln.startswith("Requires-Dist:") and "torch" in ln]
    assert extras and all("extra == \"train\"" in ln for ln in extras)
    # and what those pull in turn, from the installed distributions' own metadata (markers
    # evaluated for this machine): the set a no-extras install brings, read without a network
    closure = requirement_closure([ln.split(":", 1)[1].strip() for ln in base])
    assert {"numpy", "onnxruntime", "pyserial"} <= closure
    assert not closure & {"torch", "onnx", "onnxscript", "pyemd", "emd-signal", "scipy"}, closure
    # the wheel carries every stage and the protocol spec, not only what the editable install sees
    for module in ("tactile/runtime/commands/run.py", "tactile/training/emd/module.py",
                   "tactile/export/commands/export.py",
                   "tactile/device/PROTOCOL.md", "tactile/contract.py",
                   "tactile/runtime/web/index.html", "tactile/runtime/web/app.js",
                   "tactile/runtime/web/style.css"):
        assert module in names, module


def requirement_closure(requirements: list[str]) -> set[str]:
    """Names of the distributions that ``requirements`` need, transitively, as the versions
    installed here declare them (a dependency's own extras, ``foo[bar]``, are followed)."""
    from importlib.metadata import PackageNotFoundError, requires

    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    seen: set[str] = set()
    todo = [(r, frozenset()) for r in requirements]
    while todo:
        text, extras = todo.pop()
        req = Requirement(text)
        if req.marker is not None and not any(
                req.marker.evaluate({"extra": e}) for e in (extras or {""})):
            continue
        name = canonicalize_name(req.name)
        key = f"{name}[{','.join(sorted(req.extras))}]"
        if key in seen:
            continue
        seen.add(key)
        try:
            todo += [(r, frozenset(req.extras)) for r in requires(name) or []]
        except PackageNotFoundError:  # pragma: no cover  (the test environment has them all)
            raise AssertionError(f"{name} is required but not installed here") from None
    return {k.split("[")[0] for k in seen}


_BLOCK_TRAIN = (
    "import sys\n"
    "class Block:\n"
    "    def find_spec(self, name, path=None, target=None):\n"
    "        if name.split('.')[0] in ('torch', 'onnx', 'onnxscript'):\n"
    "            raise ModuleNotFoundError(f'No module named {name!r}', name=name)\n"
    "sys.meta_path.insert(0, Block())\n"
)


def test_commands_needing_an_extra_say_so_in_one_line():
    """On a board (no torch, no onnx) the training and export commands are installed too; each
    answers --version and --help, and a run names the extra it needs instead of printing an
    import traceback."""
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    runs = {"tactile-train": ["data"], "tactile-eval": ["run", "data"],
            "tactile-export": ["run", "-o", "model.onnx"]}
    for prog, argv in runs.items():
        module, func = scripts[prog].split(":")
        for args, code in ((["--version"], 0), (["--help"], 0), (argv, 1)):
            script = _BLOCK_TRAIN + f"from {module} import {func}\nsys.argv = {[prog, *args]!r}\n" \
                f"sys.exit({func}())\n"
            out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
            assert out.returncode == code, (prog, args, out.stderr)
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"{prog}: error: needs the [train] extra")
        assert "pip install 'tactile-pen[train]'" in lines[0]


def test_every_command_runs_with_its_dependencies():
    """The same entry points, with everything installed, reach the command's own --help."""
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    assert len(scripts) == 13
    for prog, target in scripts.items():
        module, func = target.split(":")
        code = f"import sys\nfrom {module} import {func}\nsys.argv = ['{prog}', '--help']\n" \
            f"sys.exit({func}())\n"
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
        assert out.returncode == 0, (prog, out.stderr)
        assert out.stdout.startswith(f"usage: {prog}"), (prog, out.stdout[:80])
        assert "``" not in out.stdout, prog  # docstring markup is shown as plain text


def test_a_bad_argument_is_one_line_and_exit_1():
    """argparse's own exit code 2 would read as "device or port"; every command uses 1."""
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    for prog, target in scripts.items():
        module, func = target.split(":")
        code = f"import sys\nfrom {module} import {func}\n" \
            f"sys.argv = ['{prog}', '--no-such-option']\nsys.exit({func}())\n"
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
        assert out.returncode == 1, (prog, out.returncode, out.stderr)
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"{prog}: error: "), (prog, lines)


def test_tactile_check_on_a_board_checks_what_the_runtime_loads(tmp_path):
    """Without onnx and torch, tactile-check validates with onnxruntime only and runs a window;
    a broken file is still exit 3, and the options that need PyTorch name the extra."""
    shipped = REPO / "models" / "pen-exp2.onnx"
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not onnx")

    def check(*args):
        code = _BLOCK_TRAIN + "from tactile.export.commands.check import main\n" \
            f"sys.exit(main({list(args)!r}))\n"
        return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)

    out = check(str(shipped))
    assert out.returncode == 0, out.stderr
    assert "contract ok" in out.stdout and "with onnxruntime only" in out.stdout
    assert "opset" not in out.stdout.splitlines()[0]  # not checked here, so not claimed
    out = check(str(junk))
    assert out.returncode == 3 and "not a loadable ONNX model" in out.stderr
    out = check(str(shipped), "--data", str(tmp_path))
    assert out.returncode == 1 and "need the [train] extra" in out.stderr
    full = subprocess.run([sys.executable, "-m", "tactile.export.commands.check", str(shipped)],
                          capture_output=True, text=True)
    assert full.returncode == 0 and "opset 18" in full.stdout.splitlines()[0], full.stderr
