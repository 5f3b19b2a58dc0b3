#!/usr/bin/env python3
"""A robot loop with the shape of LeRobot's async `RobotClient`, on `kairos.Client`.

LeRobot's async inference (lerobot.async_inference.robot_client) runs a control loop that, every
control period,

  1. sends an observation when the action queue has run below `chunk_size_threshold` of a chunk,
  2. executes the next action from the queue,

while a second thread receives action chunks from the policy server and fills the queue. Here the
same loop runs on `kairos.Client`: a sender thread runs `client.infer` (which releases the GIL, so
the control loop keeps its rate while the chunk is generated), and the client's action queue does
what LeRobot's receiver thread and queue do, with Kairos's alignment rule (actions whose time passed
during generation are skipped; the new chunk replaces the rest of the old one). Every action taken
with `client.next_action()` is reported to the server with the next round (Last Exec Info), which
is what the execution-aware scheduler orders robots by.

Without hardware it drives `SimulatedRobot`. `LeRobotAdapter` wraps a LeRobot `Robot` (its
`get_observation()` / `send_action()` dicts) for a real arm; it is not exercised without one.

    kairos serve &                                   # writes kairos-data/ (pin, token)
    python sdk/python/examples/lerobot_robot.py --steps 300 --fps 30
"""

import argparse
import queue
import threading
import time
from typing import Dict, Optional

import numpy as np

import kairos


class SimulatedRobot:
    """A joint-space arm that moves by the actions it is sent, with one camera."""

    def __init__(self, state_dim: int, action_dim: int, camera=(96, 128)):
        self.state = np.zeros(state_dim, dtype=np.float32)
        self.action_dim = action_dim
        self.camera = camera
        self.actions_done = 0

    def get_observation(self) -> Dict[str, object]:
        height, width = self.camera
        level = int(128 + 100 * np.tanh(self.state[:1].sum())) if self.state.size else 128
        frame = np.full((height, width, 3), level, dtype=np.uint8)
        return {"observation.state": self.state.copy(), "observation.images.front": frame}

    def send_action(self, action: np.ndarray) -> None:
        n = min(self.state.size, action.size)
        self.state[:n] += 0.05 * np.clip(action[:n], -1.0, 1.0)
        self.actions_done += 1


class LeRobotAdapter:
    """A LeRobot `Robot` (lerobot.robots) seen as the loop's robot: motor positions become the
    state vector (in `robot.action_features` order), cameras become images."""

    def __init__(self, robot):
        self.robot = robot
        self.motors = list(robot.action_features)

    def get_observation(self) -> Dict[str, object]:
        raw = self.robot.get_observation()
        observation = {"observation.state": np.array([raw[m] for m in self.motors], dtype=np.float32)}
        for key, value in raw.items():
            if isinstance(value, np.ndarray) and value.ndim == 3:
                observation[f"observation.images.{key}"] = value
        return observation

    def send_action(self, action: np.ndarray) -> None:
        self.robot.send_action({m: float(a) for m, a in zip(self.motors, action)})


class RobotClient:
    """LeRobot's RobotClient loop on kairos.Client."""

    def __init__(self, client: kairos.Client, robot, task: str, fps: float, chunk_size_threshold: float):
        self.client = client
        self.robot = robot
        self.task = task
        self.period = 1.0 / fps
        self.fps = fps
        self.threshold = chunk_size_threshold
        self._observations: "queue.Queue[Optional[dict]]" = queue.Queue(maxsize=1)
        self._sending = threading.Event()
        self._error: Optional[BaseException] = None
        self.rounds = 0
        self.idle_steps = 0

    def _sender(self) -> None:
        """LeRobot's send/receive threads: one round at a time; the reply fills the queue."""
        while (observation := self._observations.get()) is not None:
            try:
                self.client.infer(observation)
                self.rounds += 1
            except kairos.Overloaded:
                time.sleep(0.05)  # the server asked us to come back later; the loop will resend
            except BaseException as error:  # surfaced by the control loop
                self._error = error
            finally:
                self._sending.clear()

    def _ready_to_send_observation(self) -> bool:
        return not self._sending.is_set() and self.client.wants_request()

    def control_loop(self, steps: int) -> Dict[str, int]:
        # A stale queued observation is re-fetched from the robot (Kairos's re-fetch, §3.2).
        fresh = lambda: {**self.robot.get_observation(), "task": self.task}  # noqa: E731
        self.client.start_task(control_hz=self.fps, trigger=self.threshold, observation_source=fresh)
        sender = threading.Thread(target=self._sender, name="kairos-sender", daemon=True)
        sender.start()
        executed = 0
        try:
            next_tick = time.monotonic()
            while executed < steps:
                if self._error is not None:
                    raise self._error
                if self._ready_to_send_observation():
                    observation = self.robot.get_observation()
                    observation["task"] = self.task
                    self._sending.set()
                    self._observations.put(observation)
                action = self.client.next_action()
                if action is None:
                    self.idle_steps += 1  # the queue ran dry: the robot waits for a chunk
                else:
                    self.robot.send_action(action)
                    executed += 1
                next_tick += self.period
                time.sleep(max(0.0, next_tick - time.monotonic()))
        finally:
            self._observations.put(None)
            sender.join()
        record = self.client.end_task()
        return {"executed": executed, "rounds": self.rounds, "idle_steps": self.idle_steps,
                "server_rounds": record["rounds"], "wait_us": record["wait_us"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data-dir", default="kairos-data", help="the server's data directory (pin, token)")
    parser.add_argument("--server", default="127.0.0.1:4433", help="the server's UDP address")
    parser.add_argument("--steps", type=int, default=300, help="actions to execute")
    parser.add_argument("--fps", type=float, default=30.0, help="control frequency, actions per second")
    parser.add_argument("--threshold", type=float, default=0.5,
                        help="LeRobot's chunk_size_threshold: request the next chunk at this executed fraction")
    parser.add_argument("--task", default="pick up the cube", help="the instruction")
    args = parser.parse_args()

    with kairos.Client.from_data_dir(args.data_dir, args.server) as client:
        model = client.model
        robot = SimulatedRobot(model["state_dim"], model["action_dim"])
        loop = RobotClient(client, robot, args.task, args.fps, args.threshold)
        summary = loop.control_loop(args.steps)
    print(f"model {model['name']}: executed {summary['executed']} actions in {summary['rounds']} rounds "
          f"({summary['idle_steps']} idle control steps; the server recorded {summary['server_rounds']} rounds, "
          f"{summary['wait_us'] / 1e3:.1f} ms waiting)")


if __name__ == "__main__":
    main()
