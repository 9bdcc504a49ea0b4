"""Joint log CSV: t, q1..qn, v1..vn, optional a1..an, tau1..taun, extra columns, read into and
written from the JointLog of systems/model/joint_data.py."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
from safesysid.systems.model.joint_data import JointLog


class LogError(ValueError):
    """Bad joint log; the message names file, row and column."""


def _joint_count(header):
    n = 0
    while f"q{n + 1}" in header:
        n += 1
    return n


def _read_rows(path: Path) -> list[list[str]]:
    try:
        with path.open(newline="") as fh:
            rows = list(csv.reader(fh))
    except OSError as err:
        raise LogError(f"{path}: cannot read ({err.strerror})") from err
    if not rows:
        raise LogError(f"{path}: empty file")
    return rows


def _columns_read(path: Path, header: list[str], n_joints: int | None) -> tuple[int, set[str], bool]:
    """(joints, the columns we read, whether a1..an are among them) of a header; LogError naming
    the first missing column."""
    if "t" not in header:
        raise LogError(f"{path}: row 1: missing column 't'")
    n = _joint_count(header)
    if n == 0:
        raise LogError(f"{path}: row 1: missing columns q1..qn")
    if n_joints is not None and n != n_joints:
        raise LogError(f"{path}: row 1: the log has {n} joints (q1..q{n}), the model has {n_joints}")
    need = [f"{p}{k}" for p in ("q", "v", "tau") for k in range(1, n + 1)]
    for col in need:
        if col not in header:
            raise LogError(f"{path}: row 1: missing column '{col}'")
    has_a = all(f"a{k}" in header for k in range(1, n + 1))
    return n, {"t", *need, *([f"a{k}" for k in range(1, n + 1)] if has_a else [])}, has_a


def _numbers(path: Path, rows: list[list[str]], header: list[str], known: set[str]) -> np.ndarray:
    """The data rows as numbers; a cell of an extra column that is no number becomes NaN."""
    if len(rows) < 2:
        raise LogError(f"{path}: no data rows")
    data = np.empty((len(rows) - 1, len(header)))
    for r, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise LogError(f"{path}: row {r}: {len(row)} values, header has {len(header)}")
        for c, cell in enumerate(row):
            try:
                data[r - 2, c] = float(cell)
            except ValueError:
                if header[c] in known:
                    raise LogError(f"{path}: row {r}, column '{header[c]}': not a number ({cell!r})") from None
                data[r - 2, c] = np.nan  # an extra column we do not read
    used = [k for k, h in enumerate(header) if h in known]  # extra columns are not ours to judge
    bad = ~np.isfinite(data[:, used])
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise LogError(f"{path}: row {r + 2}, column '{header[used[c]]}': NaN or inf")
    return data


def read_joint_log(path: str | Path, n_joints: int | None = None) -> JointLog:
    """Read and validate a joint log; LogError (one line) on any problem."""
    path = Path(path)
    rows = _read_rows(path)
    header = [h.strip() for h in rows[0]]
    n, known, has_a = _columns_read(path, header, n_joints)
    data = _numbers(path, rows, header, known)
    col = {h: data[:, k] for k, h in enumerate(header)}
    t = col["t"]
    step = np.diff(t)
    if np.any(step <= 0):
        r = int(np.flatnonzero(step <= 0)[0]) + 3
        raise LogError(f"{path}: row {r}, column 't': time is not strictly increasing")
    stack = lambda p: np.stack([col[f"{p}{k}"] for k in range(1, n + 1)], 1)  # noqa: E731
    extra = {h: col[h] for h in header if h not in known}
    return JointLog(t, stack("q"), stack("v"), stack("tau"), stack("a") if has_a else None, extra, str(path))


def write_joint_log(path: str | Path, log: JointLog, extra_columns: dict[str, np.ndarray] | None = None) -> Path:
    """Write a joint log (plus extra named columns)."""
    n = log.n
    cols = {"t": log.t}
    cols.update({f"q{k + 1}": log.q[:, k] for k in range(n)})
    cols.update({f"v{k + 1}": log.v[:, k] for k in range(n)})
    if log.a is not None:
        cols.update({f"a{k + 1}": log.a[:, k] for k in range(n)})
    cols.update({f"tau{k + 1}": log.tau[:, k] for k in range(n)})
    cols.update(log.extra)
    cols.update(extra_columns or {})
    names = list(cols)
    table = np.column_stack([np.asarray(cols[k], float) for k in names])
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, table, delimiter=",", header=",".join(names), comments="", fmt="%.10g")
    return path
