"""Template: a horizon-policy plugin in Python (componentize-py).

"bound": execute the prefix of the chunk whose final-step updates are all at most `bound`
(an absolute L2 norm), clamped to the robot's [h-min, h-max]. Parameter: bound (default 0.05).
The same policy is in templates/c/bound.c and examples/bound_horizon.rs.

Build (templates/python/build.sh does exactly this):
    kairos plugin wit --out wit                     # the WIT this server implements
    componentize-py -d wit -w horizon-policy componentize app -o bound_py.wasm
    kairos plugin check bound_py.wasm
For editor completion: `componentize-py -d wit -w horizon-policy bindings .` writes the
`wit_world` package imported below.

A priority policy is the same with `-w priority-policy` and a class `Priority` with
`rank(self, now_us, pending, params)` and `task_finished(self, summary)`. Since
kairos:policy@0.2.0, `pending` is a `priority.PendingColumns` (one list per field, plus a
`present` bitmask for the optional ones) and `rank` returns
`priority.Ranking_Keys(priority.SortKeys(major, minor))` (the server sorts by (major, minor,
arrived-at-us, request) ascending; an empty list means all zeros) or `priority.Ranking_Order`
(a full order). Keys are much faster: no per-row sort in the interpreter. See
plugins/python/kairos/app.py for a complete one.

Raise componentize_py_types.Err(...) to decline (here with a horizon-error value); any other
exception traps the instance and the server answers that decision with its fallback policy.
Python components are ~18 MB and cost ~0.1-12 ms per call (~100 ms for a 1000-step chunk); the
server's default deadline for a component that imports WASI (500 ms) covers that, so this
template passes `kairos plugin check` at default settings.
"""

import math
from typing import List

from componentize_py_types import Err
from wit_world import exports
from wit_world.exports import horizon
from wit_world.imports import types


class Horizon(exports.Horizon):
    def choose(self, chunk: horizon.Chunk, context: horizon.HorizonContext, params: List[types.Param]) -> int:
        bound = 0.05
        for p in params:
            if p.name != "bound":
                raise Err(horizon.HorizonError_InvalidParam(types.ParamProblem(p.name, "unknown parameter (expected: bound)")))
            if not (math.isfinite(p.value) and p.value >= 0.0):
                raise Err(horizon.HorizonError_InvalidParam(types.ParamProblem("bound", "not a finite number >= 0")))
            bound = p.value
        n, d = chunk.chunk_len, chunk.action_dim
        last = (chunk.steps - 1) * n * d  # sample 0, last step
        h = 0
        while h < n:
            start = last + h * d
            norm = math.sqrt(sum(float(x) * float(x) for x in chunk.updates[start:start + d]))
            if not norm <= bound:
                break
            h += 1
        return min(max(h, context.h_min), context.h_max)
