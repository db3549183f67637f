"""Multiruns that report every job: a bad job does not stop the sweep, and the sweep ends with a summary.

Inside a Hydra multirun, :func:`difareli.errors.cli_entry` prints a job's user error, records it with
:func:`difareli.errors.record_failure` in ``<sweep dir>/failed_jobs.jsonl`` (a file, so launchers that run jobs in other
processes report too) and lets the next job run. :class:`SweepSummary`, a Hydra callback (``conf/hydra/default.yaml``),
prints ``N jobs: K completed, F failed`` with each failed job's overrides and message at the end, writes
``sweep_summary.json`` and exits with status 2 when any job failed.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback

from difareli.errors import FAILED_JOBS as FAILED
from difareli.utils.fileio import write_json_atomic

SUMMARY = "sweep_summary.json"


class SweepSummary(Callback):
    """Count the jobs of a multirun and report the failed ones at its end (exit status 2 if any)."""

    def __init__(self) -> None:
        self.jobs = 0

    def on_job_end(self, config: Any, job_return: Any, **kwargs: Any) -> None:
        self.jobs += 1

    def on_multirun_end(self, config: Any, **kwargs: Any) -> None:
        sweep = Path(config.hydra.sweep.dir)
        path = sweep / FAILED
        failed = [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.is_file() else []
        jobs = max(self.jobs, len(failed))
        summary = {"jobs": jobs, "completed": jobs - len(failed), "failed": failed}
        write_json_atomic(sweep / SUMMARY, summary)
        if not failed:
            return
        print(f"sweep {sweep}: {jobs} job(s): {jobs - len(failed)} completed, {len(failed)} failed", file=sys.stderr)
        for f in failed:
            print(f"  job {f['job']} ({' '.join(f['overrides'])}): {f['message']}", file=sys.stderr)
        sys.exit(2)
