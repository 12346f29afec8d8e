"""experiments/campaigns/session_lanes.sh: the lanes a device call starts parse and end with a done file (an empty
ONE_WARP_JOBS once left a dangling ';' that bash refused, so the lane never wrote it and every poll waited)."""

import os
import pathlib
import subprocess
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent


def test_plan_one_lane_runs_its_jobs_and_writes_its_done_file(tmp_path):
    env = {**os.environ, "SESSION_PLAN": "one", "SESSION_LANES_DIR": str(tmp_path / "lanes"), "ONE_JOBS": "setup"}
    env.pop("ONE_WARP_JOBS", None)  # none: the plan's default
    started = subprocess.run(
        ["bash", "experiments/campaigns/session_lanes.sh", "start"], cwd=ROOT, env=env, capture_output=True,
        text=True, timeout=60,
    )  # fmt: skip
    assert started.returncode == 0 and "plan one" in started.stdout, started.stderr
    done = tmp_path / "lanes" / "scaling" / "done"
    deadline = time.monotonic() + 90
    while not done.exists() and time.monotonic() < deadline:
        time.sleep(0.5)
    log = (tmp_path / "lanes" / "scaling" / "log.txt").read_text()
    assert done.exists() and done.read_text().startswith("rc="), log
    assert "syntax error" not in log and "job setup" not in log  # setup is gpu_run's listing job, not a timed one
