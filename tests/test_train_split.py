"""Named test and validation takes (``test = "trial:41-50"``, ``user:alice,bob``,
``name:*-rep5``) and split lines that name users, not indices."""

from __future__ import annotations

import json

import pytest

from tactile.device.recordings import load_dataset
from tactile.device.sim import make_dataset
from tactile.errors import ConfigError
from tactile.training.config import TrainConfig
from tactile.training.data import split_takes
from tactile.training.overrides import parse_sets

USERS = ["alice", "bob", "carol", "dave", "erin", "trial12"]


@pytest.fixture(scope="module")
def takes(tmp_path_factory):
    """6 users x 2 labels; user u's takes are trials 41 + 2u (non_contact) and 42 + 2u."""
    out = tmp_path_factory.mktemp("named")
    make_dataset(out, takes=6, textures=("non_contact", "paper"), seconds=2, seed=1)
    for p in sorted(out.glob("*.json")):
        meta = json.loads(p.read_text())
        u = int(meta["user"])
        meta["user"] = USERS[u]
        meta["trial"] = 41 + 2 * u + (meta["label"] == "paper")
        p.write_text(json.dumps(meta))
    return load_dataset(out)


def parts(takes, split):
    return [{takes[i].path.stem for i in part} for part in (split.train, split.val, split.test)]


def test_named_test_users_and_trials(takes):
    s = split_takes(takes, TrainConfig(test="user:alice,bob", seed=1))
    train, val, test = parts(takes, s)
    assert {takes[i].meta["user"] for i in s.test} == {"alice", "bob"}
    assert len(test) == 4 and not (test & train or test & val or train & val)
    assert val and train and len(train | val | test) == len(takes)
    assert "test users alice, bob (user:alice,bob);" in s.description
    s = split_takes(takes, TrainConfig(test="trial:41-44", val="trial:45,46", seed=1))
    assert sorted(takes[i].meta["trial"] for i in s.test) == [41, 42, 43, 44]
    assert sorted(takes[i].meta["trial"] for i in s.val) == [45, 46]
    assert sorted(takes[i].meta["trial"] for i in s.train) == list(range(47, 53))


def test_named_by_file_name_glob(takes):
    s = split_takes(takes, TrainConfig(split="take", test="name:paper-*", seed=2))
    _, val, test = parts(takes, s)
    assert test == {t.path.stem for t in takes if t.label == "paper"}
    assert val and not val & test


def test_only_the_validation_named_the_test_drawn(takes):
    s = split_takes(takes, TrainConfig(val="user:carol", seed=3))
    assert {takes[i].meta["user"] for i in s.val} == {"carol"}
    assert s.test and "carol" not in {takes[i].meta["user"] for i in s.test}


def test_the_split_line_names_users_not_indices(takes):
    s = split_takes(takes, TrainConfig(seed=0))
    tested = sorted({takes[i].meta["user"] for i in s.test})
    assert f"test users {', '.join(tested)};" in s.description
    s = split_takes(takes, TrainConfig(test="user:trial12"))
    assert "test users trial12 (user:trial12);" in s.description and "[" not in s.description


def test_a_selector_of_single_takes_says_when_their_users_also_train(takes):
    """test=name:... with split=user put the named take's user in test and in training (its
    other take was drawn to train) with no word, and the split line said 'train the other N
    users', counting that user."""
    s = split_takes(takes, TrainConfig(test="name:paper-user000", val="user:bob", seed=0))
    train, _, test = parts(takes, s)
    assert test == {"paper-user000"} and "non_contact-user000" in train
    assert s.shared == ("user alice has takes in test and in training "
                        "(test='name:paper-user000' names takes, not whole users): the test "
                        "figures include users seen in training")
    trained = sorted({takes[i].meta["user"] for i in s.train})
    assert s.description.endswith(f"train users {', '.join(trained)}") and "alice" in trained
    s = split_takes(takes, TrainConfig(test="user:alice", val="name:paper-user001", seed=0))
    assert s.shared.startswith("user bob has takes in validation and in training (val=")
    s = split_takes(takes, TrainConfig(test="name:paper-user00[01]", val="user:carol", seed=0))
    assert s.shared.startswith("users alice, bob have takes in test and in training (test=")
    for cfg in (TrainConfig(test="user:alice,bob", seed=1), TrainConfig(seed=0),
                TrainConfig(split="take", test="name:paper-*", seed=2)):
        assert split_takes(takes, cfg).shared is None  # whole users, or split by take


def test_takes_without_users_are_drawn_class_by_class(tmp_path):
    """Takes with no `user` (every tactile-record take) are each a group, and the draw ignored
    their classes: with 4 classes of 8 takes a class often had no validation take (early
    stopping and the label stream's calibration blind to it). Single-class groups are now
    drawn class by class: every class in every part, at the fractions' proportions."""
    textures = ("non_contact", "paper", "desk", "cardboard")
    make_dataset(tmp_path, takes=8, textures=textures, seconds=1, seed=1)
    for p in tmp_path.glob("*.json"):
        meta = json.loads(p.read_text())
        del meta["user"]
        p.write_text(json.dumps(meta))
    takes = load_dataset(tmp_path)
    for seed in range(20):
        s = split_takes(takes, TrainConfig(seed=seed))
        for part in (s.train, s.val, s.test):
            counts = {t: sum(takes[i].label == t for i in part) for t in textures}
            assert len(set(counts.values())) == 1, (seed, counts)  # 5 / 1 / 2 of each
        assert (len(s.train), len(s.val), len(s.test)) == (20, 4, 8)
    s = split_takes(takes, TrainConfig(seed=0, test="name:*-user00[01]"))
    assert {takes[i].path.stem[-7:] for i in s.test} == {"user000", "user001"}
    assert {takes[i].label for i in s.val} == set(textures)


def test_a_copied_take_in_training_and_in_test_is_named(takes, tmp_path):
    """The same recording under two names was only "read twice" on loading, and landed in
    training and in test without a word on the split; the split now names the pair and the
    part whose figures it makes no test."""
    import shutil

    from tactile.device.recordings import read_take

    for suffix in (".csv", ".json"):
        shutil.copy(takes[0].path.with_suffix(suffix), tmp_path / f"again{suffix}")
    meta = json.loads((tmp_path / "again.json").read_text())
    meta["user"] = "zoe"
    (tmp_path / "again.json").write_text(json.dumps(meta))
    both = [*takes, read_take(tmp_path / "again.csv")]
    first = takes[0].path.name  # non_contact-user000, user alice
    s = split_takes(both, TrainConfig(test="user:zoe", val="user:bob", seed=0))
    assert s.shared == (f"{first} and again.csv hold the same recording, one in training and "
                        "one in test: the test figures include a recording trained on")
    s = split_takes(both, TrainConfig(test="user:alice", val="user:zoe", seed=0))
    assert s.shared == (f"again.csv and {first} hold the same recording, one in validation "
                        "and one in test: the test figures include a recording validated on")
    for suffix in (".csv", ".json"):  # three copies: training, validation and test
        shutil.copy(tmp_path / f"again{suffix}", tmp_path / f"third{suffix}")
    meta["user"] = "yan"
    (tmp_path / "third.json").write_text(json.dumps(meta))
    three = [*both, read_take(tmp_path / "third.csv")]
    s = split_takes(three, TrainConfig(test="user:zoe", val="user:yan", seed=0))
    assert s.shared == (
        f"{first} and third.csv hold the same recording, one in training and one in validation: "
        "the validation figures include a recording trained on; "
        f"{first} and again.csv hold the same recording, one in training and one in test: the "
        "test figures include a recording trained on")
    assert split_takes(both, TrainConfig(test="user:alice,zoe", seed=0)).shared is None


@pytest.mark.parametrize("spec,message", [
    ("session:1", "no take has a 'session' field (fields: "),
    ("user:zed", "matches no take (user values: alice, bob, carol"),
    ("trial:90-99", "matches no take (trial values:"),
])
def test_selectors_that_name_nothing(takes, spec, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        split_takes(takes, TrainConfig(test=spec))


def test_bad_selectors(takes):
    with pytest.raises(ConfigError, match=r"test='alice': expected FIELD:VALUE"):
        TrainConfig(test="alice")
    with pytest.raises(ConfigError, match="split='time'"):
        TrainConfig(split="time", val="user:bob")
    with pytest.raises(ConfigError, match="both take"):
        split_takes(takes, TrainConfig(test="user:alice", val="trial:41"))
    with pytest.raises(ConfigError, match="cannot be split"):
        split_takes(takes, TrainConfig(test="user:alice,bob,carol", val="user:dave,erin,trial12"))
    assert parse_sets(["test=trial:41-50"], TrainConfig()).test == "trial:41-50"
