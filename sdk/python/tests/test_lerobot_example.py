"""examples/lerobot_robot.py runs its LeRobot-shaped loop to completion against a live server."""

import pathlib
import re
import subprocess
import sys

EXAMPLE = pathlib.Path(__file__).resolve().parents[1] / "examples" / "lerobot_robot.py"


def test_the_lerobot_style_loop_completes_its_steps(server):
    steps = 60
    run = subprocess.run(
        [sys.executable, str(EXAMPLE), "--data-dir", str(server.data_dir), "--server", server.address,
         "--steps", str(steps), "--fps", "100", "--threshold", "0.5"],
        capture_output=True, text=True, timeout=120,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    match = re.search(r"executed (\d+) actions in (\d+) rounds .*recorded (\d+) rounds", run.stdout)
    assert match, run.stdout
    executed, rounds, recorded = map(int, match.groups())
    assert executed == steps
    assert rounds >= 2, "the queue ran low at least once and the next chunk was requested"
    assert recorded == rounds, "every round the loop sent is in the server's record of the task"
