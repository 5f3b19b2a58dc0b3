"""Kairos robot client: the Rust SDK (kairos-sdk) for Python robots.

One `Client` is one robot's QUIC connection to a Kairos server. It pins the server's certificate,
authenticates with the robot's token, and reconnects by itself when the connection drops: a round
in flight is resent with the same round id and the server attaches it to the round it already has
(resume), so a round never runs twice.

A task is a sequence of rounds. Each round sends an observation and gets back a chunk of actions
`[H, action_dim]` (H is the execution horizon the server chose). The client keeps the chunk in an
action queue with the SDK's execution rules (`kairos_sdk::robot`): actions whose time passed while
the chunk was generated are skipped, and taking actions with `next_action()` is how the client
knows what was executed, which it reports with the next round (Last Exec Info) without the caller
doing anything more.
"""

import os
from typing import Any, Callable, Dict, Literal, Mapping, Optional, Union

import numpy as np
import numpy.typing as npt

__version__: str

Observation = Mapping[str, Any]
"""A dict with:

- ``"state"`` (or LeRobot's ``"observation.state"``): 1-D float32 array of ``model["state_dim"]``
  values (float64 is converted);
- ``"images"`` (optional): dict camera name → ``[height, width, channels]`` uint8 or float32
  array, or JPEG/PNG file bytes; LeRobot's ``"observation.images.<camera>"`` keys work too;
- ``"instruction"`` (or ``"task"``, ``"prompt"``; optional): the instruction text.

Anything else raises `InvalidObservation` naming the field.
"""

class KairosError(Exception):
    """Base class of the client's errors.

    ``code`` is the server's wire error code (``"invalid_observation"``, ``"overloaded"``, ...;
    docs/PROTOCOL.md) when the server answered with an error, else None. ``retryable`` says
    whether the same call may succeed later.
    """

    code: Optional[str]
    retryable: bool

class ConnectionFailed(KairosError):
    """The server could not be reached, or the connection was lost and reconnecting failed."""

class Timeout(ConnectionFailed):
    """Connecting or a round took longer than its limit, or an upload fell under the server's minimum rate (`too_slow`)."""

class Unauthorized(KairosError):
    """The server refused the robot token."""

class PinMismatch(KairosError):
    """The server's certificate is not the pinned one."""

class InvalidObservation(KairosError):
    """The observation does not fit the model or the limits; the message names the field."""

class InvalidRequest(KairosError):
    """Another argument or request field is invalid (horizon parameters, outcome, ...)."""

class Overloaded(KairosError):
    """The server is at capacity or shutting down; retry later."""

class ServerError(KairosError):
    """The server failed the request (e.g. generation failed)."""

class ProtocolError(KairosError):
    """The server broke the protocol, or speaks another version."""

class TaskError(KairosError):
    """The call does not fit the task's state: no task, or a round already in flight."""

class Client:
    """One robot's connection to a Kairos server."""

    def __init__(
        self,
        server: str,
        fingerprint: str,
        token: str,
        *,
        connect_timeout: float = 5.0,
        round_timeout: Optional[float] = None,
        reconnect_attempts: int = 8,
    ) -> None:
        """Connects and authenticates, blocking until the server's Welcome.

        ``server`` is ``"host:port"`` (UDP); ``fingerprint`` is the pin ``"sha256:<64 hex>"``
        that ``kairos serve`` prints and writes to ``kairos-data/fingerprint.txt``; ``token`` is
        the robot's token. The first connection is not retried, so a wrong address, pin or token
        fails at once (`ConnectionFailed`, `PinMismatch`, `Unauthorized`). Later connection losses
        are retried up to ``reconnect_attempts`` times with backoff.
        """

    @staticmethod
    def from_data_dir(
        path: Union[str, "os.PathLike[str]"] = "kairos-data",
        server: str = "127.0.0.1:4433",
        *,
        robot: str = "default",
        connect_timeout: float = 5.0,
        round_timeout: Optional[float] = None,
        reconnect_attempts: int = 8,
    ) -> "Client":
        """Connects with the pin and ``robot``'s token from a local server's data directory
        (``fingerprint.txt`` and ``tokens.toml``). Raises `KairosError` if they cannot be read."""

    @property
    def model(self) -> Dict[str, Any]:
        """The served model and connection: ``name``, ``chunk_len``, ``action_dim``,
        ``state_dim``, ``steps``, ``max_images``, ``robot`` (this token's robot name) and
        ``server`` (server software)."""

    @property
    def stats(self) -> Dict[str, int]:
        """``connects`` (1 + reconnects), ``zero_rtt_accepted``, ``resent_rounds`` (rounds resumed
        after a lost connection), ``refetches``."""

    @property
    def last_round(self) -> Optional[Dict[str, Any]]:
        """The last completed round: ``task``, ``round``, ``horizon`` (H), ``chunk_len`` (N),
        ``policy`` (the horizon policy that chose H), the server's timing in µs (``queue_us``,
        ``refetch_us``, ``inference_us``, ``total_us``) and ``batch_size``, ``attempts`` (more
        than 1 after a resume), ``refetches``, ``latency_us`` (client clock, from sending to
        the reply), and the chunking facts: ``start`` (the chunk's index the server predicted for
        the reply's arrival), ``delay`` (its predicted d, control steps from the observation's
        capture to the arrival) and ``chunking`` (the strategy applied); these three are None
        from a server that does not send them. None before the first round."""

    def start_task(
        self,
        task_id: Optional[int] = None,
        *,
        control_hz: float = 30.0,
        trigger: float = 0.5,
        horizon: Optional[str] = None,
        horizon_params: Optional[Mapping[str, float]] = None,
        observation_source: Optional[Callable[[], Observation]] = None,
        chunking: Optional[str] = None,
        alignment: str = "executed",
    ) -> int:
        """Starts a task and returns its id (random unless given).

        ``control_hz`` is the rate the robot executes actions at; ``trigger`` is the executed
        fraction of a chunk at which `wants_request` turns true (LeRobot's
        ``chunk_size_threshold``). ``horizon`` names the server's horizon policy (``"threshold"``,
        ``"static"`` or a plugin) and ``horizon_params`` its parameters, e.g. ``{"h": 10}``; None
        uses the server's default. ``observation_source`` is called (on a client thread) when the
        server finds a queued observation stale and asks for a fresh one (re-fetch); without it, or
        if it raises, the observation already sent goes again. ``chunking`` names the server's
        strategy for the actions executed while a round is in flight (``"skip"``,
        ``"from_start"``, ``"arrival_state"``, ``"rtc"``, ``"rtc_vjp"``, ``"inpaint"``,
        ``"ensemble"``; None: the server's default; docs/PROTOCOL.md §12). ``alignment`` is where
        an arriving chunk starts executing: ``"executed"`` skips the actions taken with
        `next_action` since its observation was sent, ``"server_start"`` skips as many as the
        reply's start index says. `infer` starts a task with the defaults if none is running.
        Raises `TaskError` if a task is running.
        """

    @property
    def task_id(self) -> Optional[int]:
        """The running task's id, or None."""

    def infer(self, observation: Observation) -> npt.NDArray[np.float32]:
        """Runs one round and returns the chunk's actions, ``[H, action_dim]`` float32.

        Blocks until the reply without holding the GIL, so other Python threads run meanwhile.
        The returned array owns the reply's buffer (no copy). The chunk also replaces the action
        queue (`next_action`). A lost connection is resumed transparently. Raises
        `InvalidObservation` for an observation that does not fit, `TaskError` if a round of the
        task is already in flight, and the other `KairosError` subclasses.
        """

    async def infer_async(self, observation: Observation) -> npt.NDArray[np.float32]:
        """`infer` for asyncio: the round runs on the client's own runtime and the awaitable
        resolves on the caller's event loop. The round is sent when this is called, not when it is
        awaited. Cancelling the awaitable does not cancel the round; its chunk still lands in the
        action queue."""

    def wants_request(self) -> bool:
        """Whether the next round is due: no round in flight, and the running chunk has reached
        the trigger fraction (or run out, or there is none)."""

    @property
    def in_flight(self) -> bool:
        """Whether a round is in flight."""

    @property
    def queue_size(self) -> int:
        """Actions queued for execution."""

    def next_action(self) -> Optional[npt.NDArray[np.float32]]:
        """The action to execute now, ``[action_dim]`` float32, or None if the queue is empty.
        Taking it records that it executed now; the next round reports that to the server."""

    def end_task(self, outcome: Literal["done", "failed"] = "done") -> Dict[str, int]:
        """Ends the running task (the execution so far is reported with it) and returns the
        server's record: ``task``, ``rounds``, ``wait_us``, ``attained_service_us``. Raises
        `TaskError` if no task runs or a round is in flight."""

    def now_us(self) -> int:
        """Microseconds on the client clock, the clock of every timestamp sent to the server."""

    def close(self) -> None:
        """Closes the connection; later calls raise `ConnectionFailed`."""

    def __enter__(self) -> "Client": ...
    def __exit__(self, *args: object) -> None: ...
