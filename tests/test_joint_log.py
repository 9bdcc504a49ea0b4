import numpy as np
import pytest
from safesysid.joint_log import LogError, read_joint_log, write_joint_log
from safesysid.systems.model.joint_data import JointLog


def make_log(n=3, rows=5, with_a=True):
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.001, 0.002, rows))
    mats = rng.normal(size=(4, rows, n))
    return JointLog(t, mats[0], mats[1], mats[3], mats[2] if with_a else None)


def test_round_trip_with_extra_columns(tmp_path):
    log = make_log()
    path = write_joint_log(tmp_path / "log.csv", log, {"qd1": np.arange(5.0)})
    back = read_joint_log(path, 3)
    assert np.allclose(back.q, log.q) and np.allclose(back.a, log.a) and np.allclose(back.extra["qd1"], np.arange(5))
    no_a = read_joint_log(write_joint_log(tmp_path / "b.csv", make_log(with_a=False)))
    assert no_a.a is None


def corrupt(tmp_path, edit):
    path = write_joint_log(tmp_path / "log.csv", make_log())
    lines = path.read_text().splitlines()
    edit(lines)
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize(
    "edit, expect",
    [
        (lambda l: l.__setitem__(0, l[0].replace("tau2", "tauX")), "missing column 'tau2'"),
        (lambda l: l.__setitem__(3, "nan" + l[3][l[3].index(",") :]), "row 4, column 't'"),
        (lambda l: l.__setitem__(2, l[1]), "not strictly increasing"),
        (lambda l: l.__setitem__(2, l[2] + ",1"), "row 3"),
    ],
)
def test_bad_logs_name_row_and_column(tmp_path, edit, expect):
    with pytest.raises(LogError, match=expect):
        read_joint_log(corrupt(tmp_path, edit), 3)


def test_joint_count_must_match_the_model(tmp_path):
    path = write_joint_log(tmp_path / "log.csv", make_log())
    with pytest.raises(LogError, match="the model has 7"):
        read_joint_log(path, 7)


def test_extra_columns_are_not_judged(tmp_path):
    """Contract: readers ignore columns they do not know, even NaN or text in them."""
    log = make_log()
    path = write_joint_log(tmp_path / "log.csv", log, {"note": np.full(5, np.nan)})
    assert np.allclose(read_joint_log(path, 3).q, log.q)
