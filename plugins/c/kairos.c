/*
 * Kairos wait-ratio priority policy: Algorithm 1, phases 1-2, of the paper (§3.2).
 *
 * Twin of the server's native `kairos` policy (server/src/scheduler/kairos.rs); the same
 * order bit for bit, checked by server/tests/plugin_twins.rs. Times in whole microseconds
 * (ns / 1000, truncating):
 *   1. w = wait_us / (now_us - task_started_us) in double, clamped to [0, 1]; 0 when the task
 *      started at `now`.
 *   2. With B buckets: b = min(B-1, floor(w*B)); if skipped >= A: b = min(B-1, b + skipped/A).
 *      With B = inf: the priority is the bit pattern of w itself (same order as w for w >= 0).
 *   3. Within a priority, e = |E_last|_us * (1 + skipped) descending, an exact 128-bit product
 *      (|E_last| = 0 when unknown); skipped entirely with intra_fifo = 1.
 *   4. Then arrived-at-us ascending, then request ascending.
 * Parameters (defaults): buckets B (10; whole 1..1e6, or +inf), aging A (4; whole 1..2^32-1),
 * intra_fifo (0; 1 orders each bucket by arrival: the paper's intra-bucket ablation).
 */
#include <stdlib.h>

#include "priority_policy.h"
#include "kairos_policy.h"

typedef exports_kairos_policy_priority_pending_t pending_t;
typedef unsigned __int128 u128;

typedef struct {
    uint64_t priority; /* descending */
    u128 exec;         /* descending */
    uint64_t arrived;  /* ascending */
    uint64_t request;  /* ascending */
    uint32_t index;
} sort_key_t;

static int by_key(const void *a, const void *b) {
    const sort_key_t *x = a, *y = b;
    if (x->priority != y->priority) return x->priority > y->priority ? -1 : 1;
    if (x->exec != y->exec) return x->exec > y->exec ? -1 : 1;
    if (x->arrived != y->arrived) return x->arrived < y->arrived ? -1 : 1;
    if (x->request != y->request) return x->request < y->request ? -1 : 1;
    return 0;
}

bool exports_kairos_policy_priority_order(uint64_t now_us,
                                          exports_kairos_policy_priority_list_pending_t *pending,
                                          exports_kairos_policy_priority_list_param_t *params,
                                          priority_policy_list_u32_t *ret,
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
        size_t n = pending->len;
        sort_key_t *keys = n ? malloc(n * sizeof(sort_key_t)) : NULL;
        ret->len = n;
        ret->ptr = n ? malloc(n * sizeof(uint32_t)) : NULL;
        if (n && (!keys || !ret->ptr)) abort();
        uint64_t top = (uint64_t)(buckets > 1 ? buckets : 1) - 1;
        uint32_t a = aging > 1 ? aging : 1;
        for (size_t i = 0; i < n; i++) {
            const pending_t *v = &pending->ptr[i];
            double w = kairos_wait_ratio(now_us, v->task_started_at_us, v->wait_ns);
            uint64_t priority;
            if (infinite) {
                memcpy(&priority, &w, sizeof priority);
            } else {
                uint64_t b = (uint64_t)floor(w * (double)buckets);
                if (b > top) b = top;
                if (v->skipped >= a) {
                    b += v->skipped / a;
                    if (b > top) b = top;
                }
                priority = b;
            }
            u128 exec = 0;
            if (!intra_fifo) {
                uint64_t exec_us = v->last_exec_ns.is_some ? v->last_exec_ns.val / 1000 : 0;
                exec = (u128)exec_us * ((u128)1 + v->skipped);
            }
            keys[i] = (sort_key_t){priority, exec, v->arrived_at_us, v->request, (uint32_t)i};
        }
        qsort(keys, n, sizeof(sort_key_t), by_key);
        for (size_t i = 0; i < n; i++) ret->ptr[i] = keys[i].index;
        free(keys);
    }
    exports_kairos_policy_priority_list_pending_free(pending);
    exports_kairos_policy_priority_list_param_free(params);
    return ok;
}

void exports_kairos_policy_priority_task_finished(exports_kairos_policy_priority_finished_task_t *summary) {
    (void)summary;
}
