"""FIFO priority policy in Python: the componentize-py path.

Twin of the server's native `fifo` policy (server/src/scheduler/fifo.rs): pending requests
sorted by (arrived-at-us, request) ascending. Python integers are exact, so the order is
identical to the native one by construction.
"""

from typing import List

from componentize_py_types import Err
from wit_world import exports
from wit_world.exports import priority
from wit_world.imports import types


class Priority(exports.Priority):
    def order(self, now_us: int, pending: List[priority.Pending], params: List[types.Param]) -> List[int]:
        if params:
            raise Err("fifo takes no parameters")
        return sorted(range(len(pending)), key=lambda i: (pending[i].arrived_at_us, pending[i].request))

    def task_finished(self, summary: priority.FinishedTask) -> None:
        pass
