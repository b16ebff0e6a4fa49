"""The contract's granular keys: ``signals`` and ``modalities``, the new models, the versions.

Hand-written metadata (no torch): a two-finger-like layout with one high-rate signal of 4
sub-samples per frame, a pressure channel and two electrodes. Every bad value must be refused
by ``ModelContract.from_metadata`` in one line naming the key (exit 3 in the commands).
"""

from __future__ import annotations

import json

import pytest

from tactile.contract import (
    FORMAT_VERSION,
    PREPROCESSING_VERSION,
    ModalitySpec,
    ModelContract,
    SignalSpec,
)
from tactile.errors import ModelContractError

CHANNELS = ("pac_0", "pac_1", "pac_2", "pac_3", "pdc", "ele_0", "ele_1")
SIGNAL = SignalSpec("pac", CHANNELS[:4], 400.0)
MODS = (
    ModalitySpec("vibration", CHANNELS[:4], True, 400.0, 3, 4, 20, 2),
    ModalitySpec("pressure", ("pdc",), False, 100.0, 2, 5, 10, 1),
    ModalitySpec("electrodes", ("ele_0", "ele_1"), False, 100.0, 0, 5, 10, 1),
)


def _contract(**change) -> ModelContract:
    args = dict(
        classes=("cork", "foam"), channels=CHANNELS, units=("count",) * 7, sample_rate_hz=100.0,
        window=20, hop=20, state_mode="window", model="sf_rnn", state_layers=4,
        state_hidden=50,
        preprocessing={"mean": [0.0] * 7, "std": [1.0] * 7, "center": [], "emd": None,
                       "sifts": 5},
        package_version="0.1.0", training_metrics={}, parity={"passed": True},
        signals=(SIGNAL,), modalities=MODS,
    )
    args.update(change)
    return ModelContract(**args)


def _meta(**change) -> dict[str, str]:
    meta = _contract().to_metadata()
    meta.update(change)
    return {k: v for k, v in meta.items() if v is not None}


def _mods(i: int, **change) -> str:
    mods = [m.to_json() for m in MODS]
    mods[i].update(change)
    return json.dumps(mods)


def test_granular_contract_round_trips_with_version_2():
    meta = _meta()
    c = ModelContract.from_metadata(meta)
    assert c.to_metadata() == meta
    assert c.signals == (SIGNAL,) and c.modalities == MODS
    assert meta["tactile.format_version"] == "2" == str(FORMAT_VERSION)
    assert meta["preprocessing_version"] == "2" == str(PREPROCESSING_VERSION)
    assert json.loads(meta["modalities"])[0] == {
        "name": "vibration", "channels": list(CHANNELS[:4]), "signal": True, "rate_hz": 400.0,
        "imfs": 3, "steps": 4, "atoms": 20, "nonzero": 2}


def test_a_pen_contract_stays_version_1():
    c = _contract(model="lstm", state_layers=2, state_hidden=8, signals=(), modalities=(),
                  preprocessing={"mean": [0.0] * 7, "std": [1.0] * 7, "center": [],
                                 "emd": None})
    meta = c.to_metadata()
    assert meta["tactile.format_version"] == "1" and meta["preprocessing_version"] == "1"
    assert "signals" not in meta and "modalities" not in meta


@pytest.mark.parametrize("model", ["linear", "sparse_linear"])
def test_stateless_granular_models(model):
    c = ModelContract.from_metadata(_meta(model=model, state_layers="1", state_hidden="1"))
    assert c.model == model
    with pytest.raises(ModelContractError, match=f"a {model} head's state is"):
        ModelContract.from_metadata(_meta(model=model))


def test_a_recurrent_granular_model_may_carry():
    assert ModelContract.from_metadata(_meta(state_mode="carry")).state_mode == "carry"
    with pytest.raises(ModelContractError, match="carry mode needs a recurrent model"):
        ModelContract.from_metadata(_meta(state_mode="carry", model="sparse_linear",
                                          state_layers="1", state_hidden="1"))


@pytest.mark.parametrize("change, message", [
    ({"tactile.format_version": "1"}, "'tactile.format_version': 1, but model 'sf_rnn' needs "
                                      "version 2"),
    ({"tactile.format_version": "3"}, "understands 1..2"),
    ({"preprocessing_version": "1"}, "'preprocessing_version': 1 with 'modalities'"),
    ({"preprocessing_version": "3"}, "understands 1..2"),
    ({"model": "lstm"}, "model 'lstm' takes no modalities"),
    ({"modalities": None}, "model 'sf_rnn' needs modalities"),
    ({"modalities": "[]"}, "'modalities' must be a non-empty JSON list of objects"),
    ({"modalities": "{"}, "'modalities' is not valid JSON"),
    ({"signals": '[{"name": "pac", "channels": ["pac_0"]}]'},
     "'signals': entry 0 'rate_hz' must be a number > 0"),
    ({"signals": json.dumps([{**SIGNAL.to_json(), "rate_hz": 100.0}])},
     "signal 'pac': rate_hz 100, but 4 sub-samples per frame at 100 Hz are 400 Hz"),
    ({"signals": json.dumps([{**SIGNAL.to_json(), "channels": ["pac_0", "pac_9"]}])},
     "signal 'pac': 'pac_9' is not among the channels"),
    ({"signals": json.dumps([{**SIGNAL.to_json(), "name": "pdc"}])},
     "signal name 'pdc' is used twice \\(or is a channel's name\\)"),
    ({"signals": json.dumps([SIGNAL.to_json(), {"name": "b", "channels": ["pac_3"],
                                                "rate_hz": 100.0}])},
     "channel 'pac_3' is in signals 'pac' and 'b'"),
    ({"signals": None}, "modality 'vibration': 'pac_0' is in no signal"),
    ({"modalities": _mods(0, channels=["pac_1", "pac_0", "pac_2", "pac_3"])},
     "signal 'pac' must appear whole, in time order"),
    ({"modalities": _mods(0, signal=False)}, "'pac_0' is a sub-sample of signal 'pac'"),
    ({"modalities": _mods(0, signal="yes")}, "entry 0 'signal' must be true or false"),
    ({"modalities": _mods(1, channels=["pdc", "nope"])},
     "modality 'pressure': 'nope' is not among the channels"),
    ({"modalities": _mods(1, channels=["pdc", "ele_0"])},
     "channel 'ele_0' is in modalities 'pressure' and 'electrodes'"),
    ({"modalities": _mods(1, channels=["pdc", "pdc"])}, "list of distinct names"),
    ({"modalities": _mods(2, name="pressure")}, "modality name 'pressure' is used twice"),
    ({"modalities": _mods(0, rate_hz=100.0)}, "modality 'vibration': rate_hz 100, expected 400"),
    ({"modalities": _mods(1, imfs=17)}, "imfs 17 not in 0..16"),
    ({"modalities": _mods(1, imfs=2.5)}, "entry 1 'imfs' must be an integer"),
    ({"modalities": _mods(1, steps=21)}, "modality 'pressure': steps 21 must be 1..20"),
    ({"modalities": _mods(0, steps=81)}, "modality 'vibration': steps 81 must be 1..80"),
    ({"modalities": _mods(2, nonzero=0)}, "need 1 <= nonzero <= atoms for model 'sf_rnn'"),
    ({"modalities": _mods(2, nonzero=11)}, "need 1 <= nonzero <= atoms"),
    ({"preprocessing": json.dumps({"mean": [0] * 7, "std": [1] * 7, "center": [],
                                   "emd": None})}, "'sifts' must be an integer >= 1"),
])
def test_bad_granular_values_are_named(change, message):
    with pytest.raises(ModelContractError, match=message) as e:
        ModelContract.from_metadata(_meta(**change))
    assert "\n" not in str(e.value)


def test_f_rnn_needs_no_dictionary():
    meta = _meta(model="f_rnn", modalities=_mods(2, atoms=0, nonzero=0))
    assert ModelContract.from_metadata(meta).modalities[2].atoms == 0


def test_an_old_reader_refuses_a_granular_file(monkeypatch):
    """A version-1 reader (FORMAT_VERSION 1) refuses the file by its version, in one line."""
    import tactile.contract as contract

    meta = _meta()
    monkeypatch.setattr(contract, "FORMAT_VERSION", 1)
    with pytest.raises(ModelContractError, match="'tactile.format_version' is 2; this reader "
                                                 "understands 1..1"):
        contract.ModelContract.from_metadata(meta)
