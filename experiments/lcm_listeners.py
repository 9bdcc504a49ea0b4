"""Two listeners on the arm's status channel beside a run over LCM (docs/hardware.md, Time): a
pydrake DrakeLcm and a QueuedLcm, each counting the statuses it got and the gaps in their arm time.

    safesysid arm-sim SCENARIO --out ARM &  safesysid run SCENARIO --arm lcm --out RUN &
    python experiments/lcm_listeners.py --seconds 10 [--url URL] [--channel CHANNEL]
"""

from __future__ import annotations

import argparse
import threading
import time

import numpy as np
from drake import lcmt_panda_status


def listen(lcm, channel: str, seconds: float) -> np.ndarray:
    """The arm times [s] of the statuses one listener got in `seconds` (it waits in its pump)."""
    got = []
    lcm.Subscribe(channel, got.append)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        lcm.HandleSubscriptions(20)
    return np.array([lcmt_panda_status.decode(m).utime for m in got]) * 1e-6


def report(name: str, t: np.ndarray) -> str:
    if len(t) < 2:
        return f"{name}: {len(t)} statuses"
    gaps = np.diff(t)
    return (
        f"{name}: {len(t)} statuses over {t[-1] - t[0]:.2f} s of arm time, "
        f"{int(np.sum(gaps > 1.5e-3))} gaps over 1.5 ms, longest {gaps.max() * 1e3:.1f} ms"
    )


def main() -> None:
    from pydrake.lcm import DrakeLcm
    from safesysid.systems.config import Arm
    from safesysid.systems.hardware.queued_lcm import QueuedLcm

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--url", default=Arm().lcm_url)
    parser.add_argument("--channel", default=Arm().status_channel)
    args = parser.parse_args()
    results = {}
    listeners = {"DrakeLcm": DrakeLcm(args.url), "QueuedLcm": QueuedLcm(args.url)}
    threads = [  # one process each would do as well: each listener has its own LCM instance
        threading.Thread(target=lambda n=n, lcm=lcm: results.update({n: listen(lcm, args.channel, args.seconds)}))
        for n, lcm in listeners.items()
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for name, t in results.items():
        print(report(name, t))


if __name__ == "__main__":
    main()
