"""The packet a step's samples reach the estimator in (a faulty link may deliver a late sample
beside the current one, systems/plant/faults.py SampleFaults); the estimator unpacks it."""

from __future__ import annotations

import numpy as np

# At most this many samples reach the estimator per step: a late one beside the current one from a
# faulty link; over LCM, every status that arrived since the last step (the run's loop lagging,
# or stepping every arm.run_step_ms with the controller beside the arm: ten statuses a step).
PACKET_ROWS = 32


def packet_size(n: int) -> int:
    """[count, row 0, row 1], each row [t, q (n), v (n), τ (n)]."""
    return 1 + PACKET_ROWS * (1 + 3 * n)


def pack(rows: list, n: int) -> np.ndarray:
    out = np.zeros(packet_size(n))
    out[0] = len(rows)
    for k, row in enumerate(rows):
        out[1 + k * (1 + 3 * n) : 1 + (k + 1) * (1 + 3 * n)] = row
    return out


def unpack(packet: np.ndarray, n: int) -> list:
    """The rows [t, q, v, τ] a packet carries, in delivery order."""
    width = 1 + 3 * n
    return [np.array(packet[1 + k * width : 1 + (k + 1) * width]) for k in range(int(round(packet[0])))]
