/*
 * Kairos wait-ratio priority policy: Algorithm 1, phases 1-2, of the paper (§3.2).
 *
 * Twin of the server's native `kairos` policy (server/src/scheduler/kairos.rs); the same
 * order bit for bit, checked by server/tests/plugin_twins.rs. Times in whole microseconds
 * (ns / 1000, truncating):
 *   1. w = wait_us / (now_us - task_started_us) in double, clamped to [0, 1]; 0 when the task
 *      started at `now`.
 *   2. With B buckets: b = min(B-1, floor(w*B)); if skipped >= A: b = min(B-1, b + skipped/A).
 *      Buckets are served from B-1 down: major = (B-1) - b. With B = inf: the priority is the
 *      bit pattern of w itself (same order as w for w >= 0), descending: major = UINT64_MAX - bits.
 *   3. Within a priority, e = |E_last|_us * (1 + skipped) descending, a saturating u64 product
 *      (|E_last| = 0 when unknown, i.e. present bit 0 clear): minor = UINT64_MAX - e. With
 *      intra_fifo = 1 this key is skipped: minor is empty (all 0).
 *   4. Then arrived-at-us ascending, then request ascending: the server's own tie-break.
 * Parameters (defaults): buckets B (10; whole 1..1e6, or +inf), aging A (4; whole 1..2^32-1),
 * intra_fifo (0; 1 orders each bucket by arrival: the paper's intra-bucket ablation).
 */
#include "priority_policy.h"
#include "kairos_policy.h"

/* e = |E_last|_us * (1 + skipped), saturating like the native twin: 1 + skipped reaches 2^32,
 * so the product of a huge |E_last| may not fit in 64 bits. */
static uint64_t estimated_exec(uint64_t exec_us, uint32_t skipped) {
    uint64_t factor = (uint64_t)skipped + 1;
    return exec_us > UINT64_MAX / factor ? UINT64_MAX : exec_us * factor;
}

bool exports_kairos_policy_priority_rank(uint64_t now_us,
                                         exports_kairos_policy_priority_pending_columns_t *pending,
                                         exports_kairos_policy_priority_list_param_t *params,
                                         exports_kairos_policy_priority_ranking_t *ret,
                                         priority_policy_string_t *err) {
    static const char *const known[] = {"aging", "buckets", "intra_fifo", NULL};
    bool ok = true, infinite = false, intra_fifo = false;
    uint32_t buckets = 10, aging = 4;
    const kairos_policy_types_param_t *p = kairos_param_unknown(params->ptr, params->len, known);
    if (p) {
        priority_policy_string_dup(err, "kairos: unknown parameter (expected aging, buckets, intra_fifo)");
        ok = false;
    }
    if (ok && (p = kairos_param_find(params->ptr, params->len, "buckets"))) {
        if (isinf(p->value) && p->value > 0) {
            infinite = true;
        } else if (kairos_is_count(p->value) && p->value <= 1e6) {
            buckets = (uint32_t)p->value;
        } else {
            priority_policy_string_dup(err, "kairos: buckets must be a whole number between 1 and 10^6, or inf");
            ok = false;
        }
    }
    if (ok && (p = kairos_param_find(params->ptr, params->len, "aging"))) {
        if (kairos_is_count(p->value) && p->value <= 4294967295.0) {
            aging = (uint32_t)p->value;
        } else {
            priority_policy_string_dup(err, "kairos: aging must be a whole number between 1 and 2^32-1");
            ok = false;
        }
    }
    if (ok && (p = kairos_param_find(params->ptr, params->len, "intra_fifo"))) {
        if (p->value == 0.0 || p->value == 1.0) {
            intra_fifo = p->value == 1.0;
        } else {
            priority_policy_string_dup(err, "kairos: intra_fifo must be 0 or 1");
            ok = false;
        }
    }
    if (ok) {
        size_t n = pending->request.len;
        const uint64_t *started_us = pending->task_started_at_us.ptr;
        const uint64_t *wait_ns = pending->wait_ns.ptr;
        const uint32_t *skipped = pending->skipped.ptr;
        uint64_t *major = kairos_u64s(n);
        /* One loop per case rather than a test per row: the rows are the hot path. */
        if (infinite) {
            for (size_t i = 0; i < n; i++) {
                major[i] = kairos_desc(kairos_f64_bits(kairos_wait_ratio(now_us, started_us[i], wait_ns[i])));
            }
        } else {
            uint64_t top = (uint64_t)(buckets > 1 ? buckets : 1) - 1;
            uint32_t a = aging > 1 ? aging : 1;
            for (size_t i = 0; i < n; i++) {
                double w = kairos_wait_ratio(now_us, started_us[i], wait_ns[i]);
                uint64_t b = (uint64_t)floor(w * (double)buckets);
                if (b > top) b = top;
                if (skipped[i] >= a) {
                    b += skipped[i] / a;
                    if (b > top) b = top;
                }
                major[i] = top - b;
            }
        }
        uint64_t *minor = NULL;
        if (!intra_fifo) {
            const uint64_t *exec_ns = pending->last_exec_ns.ptr;
            const uint8_t *present = pending->present.ptr;
            minor = kairos_u64s(n);
            for (size_t i = 0; i < n; i++) {
                uint64_t exec_us = present[i] & KAIROS_PRESENT_LAST_EXEC ? exec_ns[i] / 1000 : 0;
                minor[i] = kairos_desc(estimated_exec(exec_us, skipped[i]));
            }
        }
        *ret = (exports_kairos_policy_priority_ranking_t){
            .tag = EXPORTS_KAIROS_POLICY_PRIORITY_RANKING_KEYS,
            .val.keys = {{major, n}, {minor, intra_fifo ? 0 : n}},
        };
    }
    exports_kairos_policy_priority_pending_columns_free(pending);
    exports_kairos_policy_priority_list_param_free(params);
    return ok;
}

void exports_kairos_policy_priority_task_finished(exports_kairos_policy_priority_finished_task_t *summary) {
    (void)summary;
}
