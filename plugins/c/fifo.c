/*
 * FIFO priority policy: first come, first served.
 *
 * Twin of the server's native `fifo` policy (server/src/scheduler/fifo.rs): pending requests
 * ordered by (arrived-at-us, request) ascending. Nothing about the task is consulted, so the
 * answer is two empty key lists (all keys 0): the server's own tie-break, (arrived-at-us,
 * request), is the whole order.
 * Parameters: none.
 */
#include "priority_policy.h"
#include "kairos_policy.h"

bool exports_kairos_policy_priority_rank(uint64_t now_us,
                                         exports_kairos_policy_priority_pending_columns_t *pending,
                                         exports_kairos_policy_priority_list_param_t *params,
                                         exports_kairos_policy_priority_ranking_t *ret,
                                         priority_policy_string_t *err) {
    (void)now_us;
    bool ok = params->len == 0;
    if (ok) {
        *ret = (exports_kairos_policy_priority_ranking_t){.tag = EXPORTS_KAIROS_POLICY_PRIORITY_RANKING_KEYS};
    } else {
        priority_policy_string_dup(err, "fifo takes no parameters");
    }
    exports_kairos_policy_priority_pending_columns_free(pending);
    exports_kairos_policy_priority_list_param_free(params);
    return ok;
}

void exports_kairos_policy_priority_task_finished(exports_kairos_policy_priority_finished_task_t *summary) {
    (void)summary;
}
