"""Kairos wait-ratio priority policy (Algorithm 1, phases 1-2) in Python, via componentize-py.

Built against kairos:policy@0.2.0 (wit/since_v0.2.0): `rank` gets the pending requests as
columns and answers with sort keys, which the server sorts by (major, minor, arrived-at-us,
request) ascending.

Twin of the server's native `kairos` policy (server/src/scheduler/kairos.rs) and of
plugins/c/kairos.c; the same order bit for bit (server/tests/plugin_twins.rs). Python floats
are IEEE doubles and int-to-float conversion rounds to nearest-even like Rust's `as f64`, so
following the native arithmetic step by step gives identical results:
  1. w = float(wait_ns // 1000) / float(now_us - task_started_us), clamped to [0, 1]; 0 when
     the task started now (or later).
  2. B buckets: b = min(B-1, floor(w*B)); if skipped >= A: b = min(B-1, b + skipped // A).
     major = (B-1) - b, so the top bucket sorts first.
     B = inf: the priority is w itself: major = 2^64-1 - bits(w) (for w >= 0 the order of a
     double's bits is its numeric order).
  3. Within a priority, e = min(|E_last|_us * (1 + skipped), 2^64-1) descending (a saturating
     u64 product; |E_last|_us = last_exec_ns // 1000 if `present` bit 0, else 0):
     minor = 2^64-1 - e. With intra_fifo = 1 this key is skipped: minor = [] (all zeros).
  4. Then arrived-at-us ascending, then request ascending (the server's own tie-break).
Parameters (defaults): buckets (10, or inf), aging (4), intra_fifo (0).
"""

import math
import struct
from typing import List

from componentize_py_types import Err
from wit_world import exports
from wit_world.exports import priority
from wit_world.imports import types

_U64_MAX = (1 << 64) - 1
# `present` bit 0: the row's last-exec-ns is known.
_PRESENT_LAST_EXEC = 1


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


# Speed: the interpreter is the cost (0.1.0's sort of per-row tuples ran 14-54x native), so the
# keys are built with list comprehensions over zipped columns, which keep every name a local
# and avoid per-row attribute lookups and function calls.


def _wait_ratios(now_us: int, started: List[int], waits: List[int]) -> List[float]:
    # float() on both operands, not int / int: Python's int division rounds the exact
    # quotient once, while the native twin converts each operand to f64 first (they differ
    # only above 2^53 us, but the twin must match everywhere).
    return [
        (r if (r := float(wn // 1000) / float(now_us - s)) < 1.0 else 1.0) if now_us > s else 0.0
        for s, wn in zip(started, waits)
    ]


def _major(ratios: List[float], skipped: List[int], buckets: float, aging: int) -> List[int]:
    n = len(ratios)
    if buckets == math.inf:
        # All bit patterns at once: one pack and one unpack instead of two calls per row.
        bits = struct.unpack(f"<{n}Q", struct.pack(f"<{n}d", *ratios))
        return [_U64_MAX - b for b in bits]
    top = int(buckets) - 1
    # w >= 0, so int() truncation is floor(). min(top, min(top, x) + y) = min(top, x + y) for
    # y >= 0, and skipped // A is 0 exactly when skipped < A, so the aging condition and the
    # first clamp fold into one clamp: b = min(top, floor(w*B) + skipped // A).
    return [
        0 if (b := int(w * buckets) + k // aging) >= top else top - b
        for w, k in zip(ratios, skipped)
    ]


def _minor(last_exec_ns: List[int], skipped: List[int], present: List[int]) -> List[int]:
    # e = min(exec_us * (1 + skipped), 2^64-1), the native twin's saturating u64 product.
    return [
        (0 if (e := (le // 1000) * (k + 1)) >= _U64_MAX else _U64_MAX - e)
        if pr & _PRESENT_LAST_EXEC
        else _U64_MAX
        for le, k, pr in zip(last_exec_ns, skipped, present)
    ]


class Priority(exports.Priority):
    def rank(self, now_us: int, pending: priority.PendingColumns, params: List[types.Param]) -> priority.Ranking:
        buckets, aging, intra_fifo = _params(params)
        ratios = _wait_ratios(now_us, pending.task_started_at_us, pending.wait_ns)
        major = _major(ratios, pending.skipped, buckets, aging)
        minor = [] if intra_fifo else _minor(pending.last_exec_ns, pending.skipped, pending.present)
        return priority.Ranking_Keys(priority.SortKeys(major, minor))

    def task_finished(self, summary: priority.FinishedTask) -> None:
        pass
