"""ROS bag joint logs (app/joint_bag.py): every format rosbags writes (ROS 2 sqlite3, ROS 2 MCAP,
ROS 1), mapping by joint name, header stamps, and `safesysid diagnose` giving the same
diagnosis on a bag as on the CSV of the same data; bad bags -> one line naming file, topic and
field, exit 2."""

import json
from decimal import Decimal

import numpy as np
import pytest
from safesysid.cli import main
from safesysid.joint_bag import read_joint_bag
from safesysid.joint_log import LogError, read_joint_log, write_joint_log
from safesysid.systems.model.joint_data import JointLog
from safesysid.systems.model.robot_model import load_robot
from test_gap import TWO_LINK, _logs

FORMATS = ("ros2_sqlite3", "ros2_mcap", "ros1")
TOPIC = "/arm/joint_states"


def _stamp(t):
    """(sec, nanosec) of a time written in the CSV (at most 9 decimals: exact)."""
    ns = Decimal(repr(float(t))) * 10**9
    assert ns == ns.to_integral_value()
    return divmod(int(ns), 10**9)


def write_bag(path, fmt, log, names, topic=TOPIC, zero_stamps=False, extra_group=True, edit=None):
    """Write `log` as JointState messages (columns named `names`, listed in reverse order in the
    message to test the mapping by name), plus a gripper's JointState on the same topic."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)
    JointState = store.types["sensor_msgs/msg/JointState"]
    Header = store.types["std_msgs/msg/Header"]
    Time = store.types["builtin_interfaces/msg/Time"]
    header_extra = {"seq": 0} if "seq" in Header.__dataclass_fields__ else {}
    serialize = store.serialize_ros1 if fmt == "ros1" else store.serialize_cdr
    order = list(range(len(names)))[::-1]

    def message(stamp, fields, joint_names):
        sec, ns = (0, 0) if zero_stamps else stamp
        header = Header(stamp=Time(sec=sec, nanosec=ns), frame_id="", **header_extra)
        return JointState(header=header, name=joint_names, **fields)

    if fmt == "ros1":
        writer = Writer1(path)
    else:
        writer = Writer(
            path, version=9, storage_plugin=StoragePlugin.MCAP if fmt == "ros2_mcap" else StoragePlugin.SQLITE3
        )
    with writer:
        con = writer.add_connection(topic, JointState.__msgtype__, typestore=store)
        for k in range(len(log)):
            stamp = _stamp(log.t[k])
            fields = {"position": log.q[k, order], "velocity": log.v[k, order], "effort": log.tau[k, order]}
            if edit:
                edit(k, fields)
            bag_time = stamp[0] * 10**9 + stamp[1]
            msg = message(stamp, fields, [names[i] for i in order])
            writer.write(con, bag_time, serialize(msg, JointState.__msgtype__))
            if extra_group and k % 10 == 3:
                grip = {"position": np.array([0.01]), "velocity": np.zeros(1), "effort": np.zeros(1)}
                writer.write(con, bag_time + 1, serialize(message(stamp, grip, ["finger"]), JointState.__msgtype__))
    return path


def bag_path(root, fmt, name):
    return root / (f"{name}.bag" if fmt == "ros1" else name)


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    """Three two-link logs (viscous friction on joint 1 withheld), as CSV and read back, so the
    bags hold exactly the floats the CSV holds."""
    root = tmp_path_factory.mktemp("bags")
    urdf = root / "two_link.urdf"
    urdf.write_text(TWO_LINK)
    model = load_robot(model_path=urdf)
    sims = _logs(model, 5, {"viscous_friction": {"delta": np.array([1.5, 0.0])}}, with_a=False, noise=0.2)
    # Absolute times like a robot clock (stamps with whole seconds).
    csvs = [write_joint_log(root / f"log{k}.csv", JointLog(100.0 + x.t, x.q, x.v, x.tau)) for k, x in enumerate(sims)]
    return root, urdf, model, csvs, [read_joint_log(p, 2) for p in csvs]


@pytest.mark.parametrize("fmt", FORMATS)
def test_bag_reads_back_the_csv_floats(logs, fmt):
    root, _, model, _, read = logs
    log = read[0]
    (root / fmt).mkdir()
    path = write_bag(bag_path(root / fmt, fmt, "one"), fmt, log, model.joint_params.names)
    back = read_joint_bag(path, TOPIC, model.joint_params.names, n_joints=2)
    for name in ("t", "q", "v", "tau"):
        assert np.array_equal(getattr(back, name), getattr(log, name)), name
    assert back.a is None
    # Zero header stamps: the bag's receive time is used instead (the same instants here).
    zero = write_bag(bag_path(root / fmt, fmt, "zero"), fmt, log, model.joint_params.names, zero_stamps=True)
    assert np.array_equal(read_joint_bag(zero, TOPIC, model.joint_params.names, n_joints=2).t, log.t)


def _same_up_to_timing(a, b, rename):
    """Equal JSON trees, except wall-clock fields; strings equal after `rename` (bag path -> CSV path)."""
    if isinstance(a, dict):
        assert set(a) == {rename(k) for k in b} or set(a) == set(b)
        for key in a:
            if "time_s" in key:
                continue
            other = b[key] if key in b else b[next(k for k in b if rename(k) == key)]
            _same_up_to_timing(a[key], other, rename)
    elif isinstance(a, list):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            _same_up_to_timing(x, y, rename)
    elif isinstance(b, str):
        assert a == rename(b)
    else:
        assert a == b


@pytest.mark.parametrize("fmt", FORMATS)
def test_diagnosis_from_bags_equals_the_csv_diagnosis(logs, fmt, capsys):
    root, urdf, model, csvs, read = logs
    folder = root / f"diag_{fmt}"
    folder.mkdir()
    names = model.joint_params.names
    bags = [write_bag(bag_path(folder, fmt, f"log{k}"), fmt, log, names) for k, log in enumerate(read)]
    out_csv, out_bag = folder / "csv", folder / "bag"
    assert (
        main(
            [
                "diagnose",
                "--model",
                str(urdf),
                "--fit",
                *map(str, csvs[:2]),
                "--check",
                str(csvs[2]),
                "--out",
                str(out_csv),
            ]
        )
        == 0
    )
    # Default joints: the model's names (j1, j2); the topic is not the default one.
    assert (
        main(
            [
                "diagnose",
                "--model",
                str(urdf),
                "--fit",
                *map(str, bags[:2]),
                "--check",
                str(bags[2]),
                "--topic",
                TOPIC,
                "--out",
                str(out_bag),
            ]
        )
        == 0
    )
    a = json.loads((out_csv / "diagnosis.json").read_text())
    b = json.loads((out_bag / "diagnosis.json").read_text())
    paths = {str(bg): str(c) for bg, c in zip(bags, csvs)}
    _same_up_to_timing(a, b, lambda s: paths.get(s, s))
    assert a["cause"] == ["viscous_friction"]

    def body(out):  # the header comment names the log files
        return [x for x in (out / "corrected_params.yaml").read_text().splitlines() if not x.startswith("#")]

    assert body(out_bag) == body(out_csv)


def _expect_bad(path, tmp_path, capsys, *words, extra=()):
    code = main(
        [
            "diagnose",
            "--model",
            str(tmp_path / "two_link.urdf"),
            "--fit",
            str(path),
            str(path),
            "--topic",
            TOPIC,
            "--out",
            str(tmp_path / "o"),
            *extra,
        ]
    )
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    for w in (str(path),) + words:
        assert w in err, (w, err)
    return err


@pytest.mark.parametrize("fmt", FORMATS)
def test_bad_bags_are_one_line_exit_2(logs, fmt, tmp_path, capsys):
    _, _, model, _, read = logs
    (tmp_path / "two_link.urdf").write_text(TWO_LINK)
    log = read[0].slice(slice(0, 50))
    names = model.joint_params.names
    good = write_bag(bag_path(tmp_path, fmt, "good"), fmt, log, names)
    _expect_bad(good, tmp_path, capsys, "/elsewhere", "not in the bag", extra=("--topic", "/elsewhere"))
    _expect_bad(good, tmp_path, capsys, TOPIC, "field name", "'j3'", extra=("--joints", "j1,j3"))

    def empty_effort(k, fields):
        if k == 7:
            fields["effort"] = np.zeros(0)

    bad = write_bag(bag_path(tmp_path, fmt, "no_effort"), fmt, log, names, edit=empty_effort)
    # The 9th message on the topic: a gripper message came first.
    _expect_bad(bad, tmp_path, capsys, TOPIC, "message 9, field effort: empty")
    back = JointLog(log.t.copy(), log.q, log.v, log.tau)
    back.t[20] = back.t[19]
    bad = write_bag(bag_path(tmp_path, fmt, "time"), fmt, back, names, extra_group=False)
    _expect_bad(bad, tmp_path, capsys, TOPIC, "message 21, field header.stamp", "not strictly increasing")


def test_not_a_bag(tmp_path):
    (tmp_path / "x.bag").write_text("not a bag")
    with pytest.raises(LogError, match="cannot open as a ROS bag"):
        read_joint_bag(tmp_path / "x.bag")


def test_sysid_on_a_bag_equals_the_csv(tmp_path, capsys):
    """`safesysid sysid` reads bags too (joints by the model's names): the same estimate."""
    from safesysid.systems import estimation as E

    robot = load_robot(coulomb_smoothing=0.01)
    rng = np.random.default_rng(4)
    t, q, v, tau, _ = E.simulate_log(
        rng, robot, robot.theta, duration_s=2.0, rate_hz=1000.0, centre=[0.0, 0.3, 0.0, 1.5, 0.0, 0.8, 0.0]
    )
    csv = write_joint_log(tmp_path / "log.csv", JointLog(t, q, v, tau))
    log = read_joint_log(csv, 7)
    bag = write_bag(tmp_path / "log_mcap", "ros2_mcap", log, robot.joint_params.names, extra_group=False)
    docs = []
    for path, extra in ((csv, []), (bag, ["--topic", TOPIC])):
        assert main(["sysid", str(path), *extra, "--out", str(tmp_path / f"out_{path.name}")]) == 0
        docs.append(json.loads((tmp_path / f"out_{path.name}" / "estimate.json").read_text()))
    for key in ("nominal", "lower", "upper", "consistent", "case"):
        assert docs[0][key] == docs[1][key]
