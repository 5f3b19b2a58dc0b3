"""Kairos wait-ratio priority policy (Algorithm 1, phases 1-2) in Python, via componentize-py.

Twin of the server's native `kairos` policy (server/src/scheduler/kairos.rs) and of
plugins/c/kairos.c; the same order bit for bit (server/tests/plugin_twins.rs). Python floats
are IEEE doubles and int-to-float conversion rounds to nearest-even like Rust's `as f64`, so
following the native arithmetic step by step gives identical results:
  1. w = wait_us / (now_us - task_started_us), clamped to [0, 1]; 0 when the task started now.
  2. B buckets: b = min(B-1, floor(w*B)); if skipped >= A: b = min(B-1, b + skipped // A).
     B = inf: the priority is w itself.
  3. Within a priority, |E_last|_us * (1 + skipped) descending (skipped with intra_fifo = 1).
  4. Then arrival ascending, then request id ascending.
Parameters (defaults): buckets (10, or inf), aging (4), intra_fifo (0).
"""

import math
from typing import List

from componentize_py_types import Err
from wit_world import exports
from wit_world.exports import priority
from wit_world.imports import types


def _is_count(v: float, most: float) -> bool:
    return math.isfinite(v) and 1.0 <= v <= most and v == math.trunc(v)


def _params(params: List[types.Param]):
    buckets, aging, intra_fifo = 10.0, 4, False
    for p in params:
        if p.name == "buckets":
            if not (p.value == math.inf or _is_count(p.value, 1e6)):
                raise Err("kairos: buckets must be a whole number between 1 and 10^6, or inf")
            buckets = p.value
        elif p.name == "aging":
            if not _is_count(p.value, 4294967295.0):
                raise Err("kairos: aging must be a whole number between 1 and 2^32-1")
            aging = int(p.value)
        elif p.name == "intra_fifo":
            if p.value not in (0.0, 1.0):
                raise Err("kairos: intra_fifo must be 0 or 1")
            intra_fifo = p.value == 1.0
        else:
            raise Err("kairos: unknown parameter (expected aging, buckets, intra_fifo)")
    return buckets, aging, intra_fifo


class Priority(exports.Priority):
    def order(self, now_us: int, pending: List[priority.Pending], params: List[types.Param]) -> List[int]:
        buckets, aging, intra_fifo = _params(params)
        infinite = buckets == math.inf
        top = max(int(buckets), 1) - 1 if not infinite else 0

        def key(i: int):
            v = pending[i]
            life = now_us - v.task_started_at_us if now_us > v.task_started_at_us else 0
            w = 0.0 if life == 0 else min(max(float(v.wait_ns // 1000) / float(life), 0.0), 1.0)
            if infinite:
                prio = w  # for w >= 0 the float order is the order of its bits
            else:
                prio = min(math.floor(w * buckets), top)
                if v.skipped >= aging:
                    prio = min(prio + v.skipped // aging, top)
            last_exec_us = v.last_exec_ns // 1000 if v.last_exec_ns is not None else 0
            exec_key = 0 if intra_fifo else last_exec_us * (1 + v.skipped)
            return (-prio, -exec_key, v.arrived_at_us, v.request)

        return sorted(range(len(pending)), key=key)

    def task_finished(self, summary: priority.FinishedTask) -> None:
        pass
