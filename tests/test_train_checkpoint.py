"""Untrusted checkpoints: a safe dict with a missing or wrong key is one line naming the file
and the key (exit 1), never a traceback."""

from __future__ import annotations

import pytest
import torch

from tactile.device.sim import make_dataset
from tactile.errors import RecordingError
from tactile.training.checkpoint import load_checkpoint
from tactile.training.commands.eval import main as eval_main
from tactile.training.config import TrainConfig
from tactile.training.train import train


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    data = tmp_path_factory.mktemp("sim")
    make_dataset(data, takes=4, textures=("non_contact", "paper"), seconds=6, seed=1)
    run = tmp_path_factory.mktemp("run")
    train(data, run, TrainConfig(epochs=1, hidden=4, layers=1, threads=1), progress=False)
    return torch.load(run / "checkpoint.pt", weights_only=True), data


def _drop(key):
    return lambda ck: ck.pop(key)


def _set(key, value):
    return lambda ck: ck.__setitem__(key, value)


def _set_config(key, value):
    return lambda ck: ck["config"].__setitem__(key, value)


def _shrink_weight(ck):
    name = next(k for k in ck["state_dict"] if k.endswith("weight"))
    ck["state_dict"][name] = ck["state_dict"][name][:1]


def _nan_weight(ck):
    w = ck["state_dict"]["head.recurrent.out.weight"].clone()
    w[0, 0] = float("nan")
    ck["state_dict"]["head.recurrent.out.weight"] = w


CASES = [  # (change, the key the message must name)
    (_drop("config"), "'config'"),
    (_set("config", [1, 2]), "'config'"),
    (_set_config("hidden", "64"), "'config'"),
    (_set_config("bogus", 1), "'config'"),
    (_set("classes", 5), "'classes'"),
    (_set("classes", ["only"]), "'classes'"),
    (_drop("channels"), "'channels'"),
    (_set("units", ["g"]), "'units'"),
    (_set("sample_rate_hz", "100"), "'sample_rate_hz'"),
    (_set("mean", [0.0]), "'mean'"),
    (_set("std", None), "'std'"),
    (_set("emd_index", [99]), "'emd_index'"),
    (_set("center_index", "all"), "'center_index'"),
    (_set("test_rows", {"a.csv": "all"}), "'test_rows'"),
    (_set("state_dict", {"x": 1}), "'state_dict'"),
    (_drop("state_dict"), "'state_dict'"),
    (_shrink_weight, "'state_dict'"),
    # read before as they were: eval gave figures of a NaN mean's model, or had its labels
    # named twice; NaN weights gave an error naming neither file nor key
    (lambda ck: ck.__setitem__("mean", [float("nan")] + list(ck["mean"])[1:]), "'mean'"),
    (lambda ck: ck.__setitem__("std", [float("inf")] + list(ck["std"])[1:]), "'std'"),
    (lambda ck: ck.__setitem__("classes", [ck["classes"][0]] * 2), "'classes'"),
    (lambda ck: ck.__setitem__("channels", [ck["channels"][0]] * len(ck["channels"])),
     "'channels'"),
    (_nan_weight, "'state_dict': head.recurrent.out.weight holds NaN or inf"),
    (_set("held_out_streams", "all"), "'held_out_streams'"),
    (_set("held_out_streams", [{"t": torch.zeros(3), "truth": torch.zeros(2, dtype=torch.long),
                                "probs": torch.zeros(3, 2)}]), "'held_out_streams'"),
    # values: they calibrate the label stream (a NaN was named as the model's output, a
    # negative probability was taken)
    *((_set("held_out_streams", [{"t": t, "truth": y, "probs": p}]), "'held_out_streams'")
      for t, y, p in (
          (torch.arange(3.0), torch.zeros(3, dtype=torch.long),
           torch.tensor([[0.5, 0.5], [float("nan"), 0.5], [0.5, 0.5]])),
          (torch.arange(3.0), torch.zeros(3, dtype=torch.long), torch.full((3, 2), -0.5)),
          (torch.arange(3.0), torch.tensor([0, 2, 0]), torch.full((3, 2), 0.5)),
          (torch.arange(3.0), torch.zeros(3), torch.full((3, 2), 0.5)),
          (torch.tensor([0.0, 2.0, 1.0]), torch.zeros(3, dtype=torch.long),
           torch.full((3, 2), 0.5)),
          (torch.zeros(0), torch.zeros(0, dtype=torch.long), torch.zeros(0, 2)))),
]


@pytest.mark.parametrize("change,key", CASES, ids=[k + str(i) for i, (_, k) in enumerate(CASES)])
def test_a_bad_key_is_one_line_naming_file_and_key(good, tmp_path, capsys, change, key):
    ck, data = good
    bad = {**ck, "config": dict(ck["config"]), "state_dict": dict(ck["state_dict"])}
    change(bad)
    path = tmp_path / "checkpoint.pt"
    torch.save(bad, path)
    with pytest.raises(RecordingError, match=key) as e:
        load_checkpoint(path)
    assert str(path) in str(e.value) and "\n" not in str(e.value)
    assert eval_main([str(tmp_path), str(data)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and key in err and "Traceback" not in err


def test_damaged_bytes_in_a_weight_are_refused(good, tmp_path, capsys):
    """Bytes flipped inside a stored tensor loaded as other weights: evaluation gave figures
    and export passed. The archive's checksums name the damaged entry."""
    ck, data = good
    path = tmp_path / "checkpoint.pt"
    torch.save(ck, path)
    raw = bytearray(path.read_bytes())
    w = ck["state_dict"]["head.recurrent.out.weight"].numpy().tobytes()
    at = bytes(raw).find(w)  # the weight's bytes, stored as they are
    assert at > 0
    raw[at : at + 4] = bytes(b ^ 0xFF for b in raw[at : at + 4])
    path.write_bytes(bytes(raw))
    with pytest.raises(RecordingError, match=r"checkpoint\.pt: damaged \(checkpoint/data/\d+ "
                       r"fails its stored checksum\): not a readable checkpoint$"):
        load_checkpoint(path)
    assert eval_main([str(tmp_path), str(data)]) == 1
    assert "damaged" in capsys.readouterr().err


def test_not_a_dict_and_not_a_checkpoint(tmp_path):
    path = tmp_path / "checkpoint.pt"
    torch.save([1, 2, 3], path)
    with pytest.raises(RecordingError, match="not a tactile checkpoint"):
        load_checkpoint(path)
    path.write_bytes(b"not a zip")
    with pytest.raises(RecordingError, match="not a readable checkpoint"):
        load_checkpoint(path)
    torch.save({"config": object()}, path)  # a pickled object: refused, never unpickled
    with pytest.raises(RecordingError) as e:
        load_checkpoint(path)
    assert str(e.value) == (f"{path}: not a readable checkpoint (it holds objects other than "
                            "tensors and plain data, which are not loaded)")
    assert "weights_only" not in str(e.value)


def test_a_checkpoint_cut_short_says_so_in_one_short_line(good, tmp_path):
    """A checkpoint cut short (a full disk, a copy stopped) was refused in torch.load's words:
    a paragraph of advice from its zip reader, ``EOFError`` when empty, and for one byte the
    false claim that it held objects other than tensors."""
    ck, _ = good
    path = tmp_path / "checkpoint.pt"
    torch.save(ck, path)
    whole = path.read_bytes()
    for n in (0, 1, 100, len(whole) // 2, len(whole) - 1):
        path.write_bytes(whole[:n])
        with pytest.raises(RecordingError) as e:
            load_checkpoint(path)
        assert str(e.value) == (f"{path}: not a readable checkpoint (not the zip archive "
                                f"torch.save writes: empty, cut short or another file; {n} "
                                "bytes)")


def test_the_good_checkpoint_loads(good, tmp_path):
    ck, _ = good
    torch.save(ck, tmp_path / "checkpoint.pt")
    model, loaded = load_checkpoint(tmp_path)
    assert loaded["classes"] == ck["classes"] and not model.training


def test_a_checkpoint_saved_before_the_wide_path_loads_without_it(tmp_path):
    """Configs saved before ``wide`` existed describe a model without it (the new default,
    on, would not fit their weights); one saved with it keeps it."""
    data = tmp_path / "sim"
    make_dataset(data, takes=4, textures=("non_contact", "paper"), seconds=6, seed=1)
    for wide in (False, True):
        run = tmp_path / f"run-{wide}"
        train(data, run, TrainConfig(epochs=1, hidden=4, layers=1, threads=1, wide=wide,
                                     ensemble=1, blend="off"), progress=False)  # as then
        ck = torch.load(run / "checkpoint.pt", weights_only=True)
        assert any(k.startswith("head.wide.") for k in ck["state_dict"]) == wide
        del ck["config"]["wide"]
        torch.save(ck, run / "checkpoint.pt")
        if wide:  # its weights do not fit a model without the path: one line, no traceback
            with pytest.raises(RecordingError, match="'state_dict' does not fit its config"):
                load_checkpoint(run)
        else:
            model, _ = load_checkpoint(run)
            assert model.head.wide is None and not model.cfg.wide


def test_a_checkpoint_saved_before_ensembles_loads_as_one_model(tmp_path):
    """Configs saved before ``ensemble`` existed describe one model (the default, 2, would
    not fit their weights); a two-member checkpoint without the key is one line, and with it
    loads as two members."""
    data = tmp_path / "sim"
    make_dataset(data, takes=4, textures=("non_contact", "paper"), seconds=6, seed=1)
    for members in (1, 2):
        run = tmp_path / f"run-{members}"
        train(data, run, TrainConfig(epochs=1, hidden=4, layers=1, threads=1,
                                     ensemble=members, blend="off"), progress=False)  # as then
        ck = torch.load(run / "checkpoint.pt", weights_only=True)
        assert any(k.startswith("head.members.1.") for k in ck["state_dict"]) == (members == 2)
        model, _ = load_checkpoint(run)
        assert model.state_shape == (members, 4)
        del ck["config"]["ensemble"]
        torch.save(ck, run / "checkpoint.pt")
        if members == 2:
            with pytest.raises(RecordingError, match="'state_dict' does not fit its config"):
                load_checkpoint(run)
        else:
            model, _ = load_checkpoint(run)
            assert model.cfg.ensemble == 1 and model.state_shape == (1, 4)
