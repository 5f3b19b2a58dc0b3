"""A priority-policy plugin in Python: first come, first served.

Build (needs componentize-py, see scripts/install-plugin-toolchains.sh):
    componentize-py -d WIT_DIR -w priority-policy componentize app -o fifo_py.wasm
    kairos plugin check fifo_py.wasm --deadline-ms 1000
where WIT_DIR holds policy.wit (`kairos plugin wit --out WIT_DIR` writes it). For IDE
completion, `componentize-py -d WIT_DIR -w priority-policy bindings .` writes the `wit_world`
package this file imports. A horizon policy is the same with `-w horizon-policy` and a class
`Horizon` with a method `choose(self, chunk, context, params) -> int`.

Errors: raise componentize_py_types.Err(message) to decline; any other exception traps the
instance, and the server answers that decision with its fallback policy.
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
