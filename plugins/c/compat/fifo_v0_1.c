/*
 * FIFO priority policy against kairos:policy@0.1.0: a compatibility fixture.
 *
 * Built against sdk/guest/c/since_v0.1.0 (the `order` function, one record per pending
 * request, sorting in the sandbox), never ported: it proves the server still loads and runs
 * plugins built for 0.1.0. plugins/c/fifo.c is the same policy for the current version.
 *
 * Twin of the server's native `fifo` policy (server/src/scheduler/fifo.rs): pending requests
 * sorted by (arrived-at-us, request) ascending. Nothing about the task is consulted.
 * Parameters: none.
 */
#include <stdlib.h>

#include "priority_policy.h"
#include "kairos_policy.h"

typedef exports_kairos_policy_priority_pending_t pending_t;

static const pending_t *g_pending;

static int by_arrival(const void *a, const void *b) {
    const pending_t *x = &g_pending[*(const uint32_t *)a];
    const pending_t *y = &g_pending[*(const uint32_t *)b];
    if (x->arrived_at_us != y->arrived_at_us) return x->arrived_at_us < y->arrived_at_us ? -1 : 1;
    if (x->request != y->request) return x->request < y->request ? -1 : 1;
    return 0;
}

bool exports_kairos_policy_priority_order(uint64_t now_us,
                                          exports_kairos_policy_priority_list_pending_t *pending,
                                          exports_kairos_policy_priority_list_param_t *params,
                                          priority_policy_list_u32_t *ret,
                                          priority_policy_string_t *err) {
    (void)now_us;
    bool ok = true;
    if (params->len > 0) {
        priority_policy_string_dup(err, "fifo takes no parameters");
        ok = false;
    } else {
        size_t n = pending->len;
        ret->len = n;
        ret->ptr = n ? malloc(n * sizeof(uint32_t)) : NULL;
        if (n && !ret->ptr) abort();
        for (size_t i = 0; i < n; i++) ret->ptr[i] = (uint32_t)i;
        g_pending = pending->ptr;
        qsort(ret->ptr, n, sizeof(uint32_t), by_arrival);
    }
    exports_kairos_policy_priority_list_pending_free(pending);
    exports_kairos_policy_priority_list_param_free(params);
    return ok;
}

void exports_kairos_policy_priority_task_finished(exports_kairos_policy_priority_finished_task_t *summary) {
    (void)summary;
}
