"""Runs on a local process pool, streamed to a JSON-lines file so an interrupted batch resumes
where it stopped (`safesysid sweep`, `safesysid compare`), with a progress line on stderr."""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

from safesysid.progress import Progress


def read_jsonl(path: Path) -> list[dict]:
    """The summaries already in a JSON-lines file (none when it does not exist)."""
    done = []
    if path.exists():
        for line in path.read_text().splitlines():
            if line.strip():
                try:
                    done.append(json.loads(line))
                except json.JSONDecodeError:  # a line cut by a crash: run that job again
                    continue
    return done


def run_pool(
    jobs: list[tuple],
    worker: Callable[..., dict],
    workers: int,
    jsonl: Path,
    describe: Callable[[tuple, dict], str],
    label: str = "runs",
) -> Iterable[tuple[tuple, dict]]:
    """Run worker(*job) for each job on `workers` processes; yield (job, summary) as each
    finishes, after appending the summary to `jsonl` (flushed and fsynced: a crash loses at
    most the runs in flight). Ctrl-C cancels the pending jobs and raises KeyboardInterrupt
    once the finished ones are on disk; describe(job, summary) is the progress note."""
    progress = Progress(len(jobs), label)
    pool = ProcessPoolExecutor(max_workers=max(1, workers))
    try:
        with jsonl.open("a") as fh:
            futures = {pool.submit(worker, *job): job for job in jobs}
            for fut in as_completed(futures):
                summary = fut.result()
                fh.write(json.dumps(summary, default=float) + "\n")
                fh.flush()
                os.fsync(fh.fileno())
                job = futures[fut]
                progress.step(describe(job, summary))
                yield job, summary
    except KeyboardInterrupt:
        print(f"\n{label}: interrupted after {progress.done}/{len(jobs)}; finished runs kept", file=sys.stderr)
        raise
    finally:
        pool.shutdown(wait=False, cancel_futures=True)
