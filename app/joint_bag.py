"""Joint logs from ROS bags (sensor_msgs/JointState), read with the `rosbags` library (no ROS
install): ROS 2 bags (a folder with metadata.yaml; sqlite3 or MCAP storage) and ROS 1 `.bag`
files. The result is the same JointLog the CSV reader returns (app/joint_log.py), so everything
downstream is shared.

Mapping: each JointState message that names the requested joints gives one sample, its columns
taken by joint NAME in the requested order (messages naming none of them, e.g. a gripper's own
JointState on the same topic, are skipped); time is the header stamp, or the bag's receive time
when the stamp is zero. JointState has no acceleration: the log has no `a` columns (the
diagnosis then uses its momentum form, as for a CSV without them).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .joint_log import JointLog, LogError, read_joint_log

JOINT_STATE_TYPES = ("sensor_msgs/msg/JointState", "sensor_msgs/JointState")
ROS2_STORAGE_SUFFIXES = (".db3", ".mcap")


def is_bag(path: str | Path) -> bool:
    """A ROS 2 bag folder (or its .db3/.mcap storage file) or a ROS 1 .bag file."""
    p = Path(path)
    return p.is_dir() or p.suffix.lower() in (".bag",) + ROS2_STORAGE_SUFFIXES


def _bag_root(path):
    """What rosbags opens: the ROS 2 bag folder (also when its storage file is given) or the .bag."""
    p = Path(path)
    if p.suffix.lower() in ROS2_STORAGE_SUFFIXES and (p.parent / "metadata.yaml").is_file():
        return p.parent
    return p


def _stamp_seconds(sec, nanosec):
    """Seconds as the float nearest to the exact decimal sec.nanosec (sec + 1e-9 nanosec would
    round twice; this way a stamp written from a CSV time reads back as the same float)."""
    return np.array([f"{s}.{ns:09d}" for s, ns in zip(sec, nanosec)], float)


def read_joint_bag(
    path: str | Path, topic: str = "/joint_states", joints: Sequence[str] | None = None, *, n_joints: int | None = None
) -> JointLog:
    """JointLog from the JointState messages of `topic`; `joints` (names, in model order) picks
    and orders the columns (default: the names of the first message that has efforts).
    LogError, one line naming file, topic and field, on any problem."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    root = _bag_root(path)
    where = f"{path}: topic {topic}"
    if not root.exists():
        raise LogError(f"{path}: bag not found")
    try:
        reader = AnyReader([root], default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    except Exception as err:  # rosbags raises its own error types per format
        raise LogError(f"{path}: cannot open as a ROS bag ({str(err).splitlines()[0]})") from err
    try:
        cons = [c for c in reader.connections if c.topic == topic]
        if not cons:
            known = sorted({c.topic for c in reader.connections})
            raise LogError(f"{path}: topic {topic}: not in the bag (topics: {', '.join(known) or 'none'})")
        if any(c.msgtype not in JOINT_STATE_TYPES for c in cons):
            raise LogError(f"{where}: message type {cons[0].msgtype}, expected sensor_msgs/JointState")
        rows = _joint_rows(reader, cons, where, joints)
    finally:
        reader.close()
    stamps, receive, q, v, tau = rows
    zero = (stamps[:, 0] == 0) & (stamps[:, 1] == 0)
    stamps[zero] = receive[zero]
    t = _stamp_seconds(stamps[:, 0], stamps[:, 1])
    bad = np.flatnonzero(np.diff(t) <= 0)
    if len(bad):
        k = int(bad[0]) + 1
        raise LogError(
            f"{where}: message {k + 1}, field header.stamp: time is not strictly increasing "
            f"({t[k]:.9f} s after {t[k - 1]:.9f} s)"
        )
    n = q.shape[1]
    if n_joints is not None and n != n_joints:
        raise LogError(f"{where}: field name: {n} joints selected, the model has {n_joints} (give --joints)")
    return JointLog(t, q, v, tau, None, {}, str(path))


def _joint_rows(reader, cons, where, joints):
    """(stamps (N, 2) int [sec, nanosec], receive stamps (N, 2), q, v, tau) of the messages
    naming the joints."""
    stamps, receive, q, v, tau = [], [], [], [], []
    names = list(joints) if joints else None
    for k, (con, t_ns, raw) in enumerate(reader.messages(connections=cons), start=1):
        msg = reader.deserialize(raw, con.msgtype)
        got = list(msg.name)
        if names is None:
            if not len(msg.effort):
                continue  # e.g. a passive joint group before the arm's first message
            names = got
        index = {name: i for i, name in enumerate(got)}
        if not any(name in index for name in names):
            continue  # another joint group on the same topic
        missing = [name for name in names if name not in index]
        if missing:
            raise LogError(f"{where}: message {k}, field name: joint {missing[0]!r} missing (has {', '.join(got)})")
        pick = [index[name] for name in names]
        for field, out in (("position", q), ("velocity", v), ("effort", tau)):
            values = np.asarray(getattr(msg, field), float)
            if len(values) != len(got):
                what = "empty" if len(values) == 0 else f"{len(values)} values for {len(got)} names"
                raise LogError(f"{where}: message {k}, field {field}: {what}")
            if not np.all(np.isfinite(values[pick])):
                raise LogError(f"{where}: message {k}, field {field}: NaN or inf")
            out.append(values[pick])
        stamps.append((msg.header.stamp.sec, msg.header.stamp.nanosec))
        receive.append(divmod(int(t_ns), 1_000_000_000))
    if not q:
        want = f"joints {', '.join(names)}" if names else "efforts"
        raise LogError(f"{where}: field name: no JointState message with {want}")
    to = lambda x: np.array(x, np.int64).reshape(-1, 2)  # noqa: E731
    return to(stamps), to(receive), np.array(q), np.array(v), np.array(tau)


def read_log(
    path: str | Path, n_joints: int | None = None, topic: str = "/joint_states", *, joints: Sequence[str] | None = None
) -> JointLog:
    """A joint log from a CSV (joint_log.py) or a ROS bag (`topic`, `joints` in model order)."""
    if is_bag(path):
        return read_joint_bag(path, topic, joints, n_joints=n_joints)
    return read_joint_log(path, n_joints)
